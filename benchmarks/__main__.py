"""Run every benchmark on one core and print the figures with their targets."""

from __future__ import annotations

import argparse
import importlib
import json
import os
import platform
import sys
import time

from shared.threads import one_blas_thread

BENCHMARKS = ["bench_radio", "bench_world", "bench_policy", "bench_training_step", "bench_sinr",
              "bench_cloud_work", "bench_adaptation", "bench_blip", "bench_correction",
              "bench_map_ceiling", "bench_jammer_count", "bench_reactive", "bench_tracking",
              "bench_late_map", "bench_jammer_placing", "bench_bus", "bench_agreement",
              "bench_planner_agreement", "bench_planner_outcomes", "bench_fleet", "bench_outbox",
              "bench_recording", "bench_console", "bench_scale", "bench_planning"]


def main() -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks", description=__doc__)
    parser.add_argument("names", nargs="*", help=f"subset of {', '.join(BENCHMARKS)}")
    parser.add_argument("--json", metavar="FILE", help="also write the figures as JSON")
    args = parser.parse_args()
    unknown = set(args.names) - set(BENCHMARKS)
    if unknown:
        parser.error(f"unknown benchmark(s): {', '.join(sorted(unknown))}")

    one_blas_thread(os.environ)
    os.environ.setdefault("JAMNAV_PLANNER_THREADS", "1")  # one core, as the targets say
    import torch

    from benchmarks.common import cpu_name

    torch.set_num_threads(1)
    print(f"CPU: {cpu_name()}")
    rows = []
    for name in args.names or BENCHMARKS:
        print(f"running {name} ...", file=sys.stderr, flush=True)
        module = importlib.import_module(f"benchmarks.{name}")
        for figure in module.run():
            rows.append(figure)
            digits = 0 if abs(figure.value) >= 100 else 1
            print(f"{figure.name:<62} {figure.value:>14,.{digits}f} {figure.unit:<10} "
                  f"{figure.verdict}")
    if args.json:
        with open(args.json, "w", encoding="utf-8") as out:
            json.dump(
                {
                    "when": time.strftime("%Y-%m-%d %H:%M:%S"),
                    "machine": f"{platform.machine()} {os.cpu_count()} cores",
                    "cpu": cpu_name(),
                    "figures": [vars(figure) for figure in rows],
                },
                out,
                indent=2,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
