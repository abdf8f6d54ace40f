/* atan2 of many pairs at once: the features' angles, five for every candidate move, cost a
 * fifth of a decision one by one. glibc's vector math library (libmvec) computes 8 (AVX-512)
 * or 4 (AVX2) at a time within 4 ulp of the exact angle, far below the float32 the features
 * are rounded to; the CPU is asked once which it may use, so the portable build runs anywhere,
 * one pair at a time on a CPU without AVX2. */
#ifndef PLANNING_ANGLES_H
#define PLANNING_ANGLES_H

#include <math.h>

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
typedef double angles_8 __attribute__((vector_size(64)));
typedef double angles_4 __attribute__((vector_size(32)));

__attribute__((target("avx512f"))) angles_8 _ZGVeN8vv_atan2(angles_8 y, angles_8 x);
__attribute__((target("avx2"))) angles_4 _ZGVdN4vv_atan2(angles_4 y, angles_4 x);

__attribute__((target("avx512f"))) static int atan2_by_8(const double *y, const double *x,
                                                        double *out, int n)
{
    int i = 0;
    for (; i + 8 <= n; i += 8) {
        angles_8 a, b;
        __builtin_memcpy(&a, y + i, sizeof a);
        __builtin_memcpy(&b, x + i, sizeof b);
        angles_8 r = _ZGVeN8vv_atan2(a, b);
        __builtin_memcpy(out + i, &r, sizeof r);
    }
    return i;
}

__attribute__((target("avx2"))) static int atan2_by_4(const double *y, const double *x,
                                                     double *out, int n)
{
    int i = 0;
    for (; i + 4 <= n; i += 4) {
        angles_4 a, b;
        __builtin_memcpy(&a, y + i, sizeof a);
        __builtin_memcpy(&b, x + i, sizeof b);
        angles_4 r = _ZGVdN4vv_atan2(a, b);
        __builtin_memcpy(out + i, &r, sizeof r);
    }
    return i;
}

static void atan2_many(const double *y, const double *x, double *out, int n)
{
    int done = 0;
    if (__builtin_cpu_supports("avx512f"))
        done = atan2_by_8(y, x, out, n);
    else if (__builtin_cpu_supports("avx2"))
        done = atan2_by_4(y, x, out, n);
    for (int i = done; i < n; i++)
        out[i] = atan2(y[i], x[i]);
}
#else
static void atan2_many(const double *y, const double *x, double *out, int n)
{
    for (int i = 0; i < n; i++)
        out[i] = atan2(y[i], x[i]);
}
#endif

#endif
