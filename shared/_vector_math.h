/* Functions of many values at once: the features' angles (five atan2 for every candidate
 * move) and the closest approaches' lengths (a hypot for each) cost a third of a decision one
 * by one, and the radio's atan2, log and exp for every point and GBS most of its time.
 * glibc's vector math library (libmvec) computes 8 (AVX-512) or 4 (AVX2) at a time within
 * 4 ulp; the CPU is asked once which it may use, so the portable build runs anywhere, one
 * value at a time on a CPU without AVX2. */
#ifndef JAMNAV_VECTOR_MATH_H
#define JAMNAV_VECTOR_MATH_H

#include <math.h>

#if defined(__x86_64__) && defined(__GNUC__) && !defined(__clang__)
typedef double pairs_8 __attribute__((vector_size(64)));
typedef double pairs_4 __attribute__((vector_size(32)));

/* name_many(a, b, out, n): out[i] = scalar(a[i], b[i]), by libmvec's fn8 and fn4 where the CPU
 * has them. */
#define VECTOR_MATH_PAIRWISE(name, scalar, fn8, fn4)                                      \
    __attribute__((target("avx512f"))) pairs_8 fn8(pairs_8 a, pairs_8 b);                    \
    __attribute__((target("avx2"))) pairs_4 fn4(pairs_4 a, pairs_4 b);                      \
    __attribute__((target("avx512f"))) static int name##_by_8(const double *a,               \
                                                              const double *b, double *out,  \
                                                              int n)                         \
    {                                                                                         \
        int i = 0;                                                                            \
        for (; i + 8 <= n; i += 8) {                                                          \
            pairs_8 x, y;                                                                     \
            __builtin_memcpy(&x, a + i, sizeof x);                                            \
            __builtin_memcpy(&y, b + i, sizeof y);                                            \
            pairs_8 r = fn8(x, y);                                                            \
            __builtin_memcpy(out + i, &r, sizeof r);                                          \
        }                                                                                     \
        return i;                                                                             \
    }                                                                                         \
    __attribute__((target("avx2"))) static int name##_by_4(const double *a, const double *b, \
                                                          double *out, int n)                \
    {                                                                                         \
        int i = 0;                                                                            \
        for (; i + 4 <= n; i += 4) {                                                          \
            pairs_4 x, y;                                                                     \
            __builtin_memcpy(&x, a + i, sizeof x);                                            \
            __builtin_memcpy(&y, b + i, sizeof y);                                            \
            pairs_4 r = fn4(x, y);                                                            \
            __builtin_memcpy(out + i, &r, sizeof r);                                          \
        }                                                                                     \
        return i;                                                                             \
    }                                                                                         \
    static void name##_many(const double *a, const double *b, double *out, int n)            \
    {                                                                                         \
        int done = 0;                                                                         \
        if (__builtin_cpu_supports("avx512f"))                                                \
            done = name##_by_8(a, b, out, n);                                                 \
        else if (__builtin_cpu_supports("avx2"))                                              \
            done = name##_by_4(a, b, out, n);                                                 \
        for (int i = done; i < n; i++)                                                        \
            out[i] = scalar(a[i], b[i]);                                                      \
    }

/* name_many(a, out, n): out[i] = scalar(a[i]), by libmvec's fn8 and fn4 where the CPU has
 * them. */
#define VECTOR_MATH_ELEMENTWISE(name, scalar, fn8, fn4)                                   \
    __attribute__((target("avx512f"))) pairs_8 fn8(pairs_8 a);                               \
    __attribute__((target("avx2"))) pairs_4 fn4(pairs_4 a);                                 \
    __attribute__((target("avx512f"))) static int name##_by_8(const double *a, double *out,  \
                                                              int n)                         \
    {                                                                                         \
        int i = 0;                                                                            \
        for (; i + 8 <= n; i += 8) {                                                          \
            pairs_8 x;                                                                        \
            __builtin_memcpy(&x, a + i, sizeof x);                                            \
            pairs_8 r = fn8(x);                                                               \
            __builtin_memcpy(out + i, &r, sizeof r);                                          \
        }                                                                                     \
        return i;                                                                             \
    }                                                                                         \
    __attribute__((target("avx2"))) static int name##_by_4(const double *a, double *out,     \
                                                          int n)                             \
    {                                                                                         \
        int i = 0;                                                                            \
        for (; i + 4 <= n; i += 4) {                                                          \
            pairs_4 x;                                                                        \
            __builtin_memcpy(&x, a + i, sizeof x);                                            \
            pairs_4 r = fn4(x);                                                               \
            __builtin_memcpy(out + i, &r, sizeof r);                                          \
        }                                                                                     \
        return i;                                                                             \
    }                                                                                         \
    static void name##_many(const double *a, double *out, int n)                             \
    {                                                                                         \
        int done = 0;                                                                         \
        if (__builtin_cpu_supports("avx512f"))                                                \
            done = name##_by_8(a, out, n);                                                    \
        else if (__builtin_cpu_supports("avx2"))                                              \
            done = name##_by_4(a, out, n);                                                    \
        for (int i = done; i < n; i++)                                                        \
            out[i] = scalar(a[i]);                                                            \
    }
#else
#define VECTOR_MATH_ELEMENTWISE(name, scalar, fn8, fn4)                                   \
    static void name##_many(const double *a, double *out, int n)                             \
    {                                                                                         \
        for (int i = 0; i < n; i++)                                                           \
            out[i] = scalar(a[i]);                                                            \
    }
#define VECTOR_MATH_PAIRWISE(name, scalar, fn8, fn4)                                      \
    static void name##_many(const double *a, const double *b, double *out, int n)            \
    {                                                                                         \
        for (int i = 0; i < n; i++)                                                           \
            out[i] = scalar(a[i], b[i]);                                                      \
    }
#endif

VECTOR_MATH_PAIRWISE(atan2, atan2, _ZGVeN8vv_atan2, _ZGVdN4vv_atan2)
VECTOR_MATH_PAIRWISE(hypot, hypot, _ZGVeN8vv_hypot, _ZGVdN4vv_hypot)
VECTOR_MATH_ELEMENTWISE(exp, exp, _ZGVeN8v_exp, _ZGVdN4v_exp)
VECTOR_MATH_ELEMENTWISE(log, log, _ZGVeN8v_log, _ZGVdN4v_log)

#endif
