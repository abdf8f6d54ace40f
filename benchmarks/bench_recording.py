"""What recording a run costs (``jamnav up --record``): the lockstep step rate of 4 agent
processes with and without the recorder, the recorder's own CPU time (steadier than a rate on
a busy machine), and the MCAP file's size per UAV-minute of flight, for a lockstep run on the
true map and for a run whose cloud learns and publishes maps."""

from __future__ import annotations

import re
import tempfile
from pathlib import Path
from statistics import median

from benchmarks.bench_bus import up_report
from benchmarks.common import Figure
from shared.scenario import load_scenario

UAVS = 4
EPISODES = "40"
REPEATS = 5  # runs with and without, alternated: on a busy machine one run says little


def _kib_per_uav_minute(recording: Path, report: dict) -> float:
    finished = next(e for e in report["events"] if e["type"] == "run_finished")
    minutes = finished["steps"] * load_scenario().timing.step_s / 60
    return recording.stat().st_size / 1024 / (UAVS * minutes)


def _recorder_cpu_per_step_us(run_dir: Path, report: dict) -> float:
    """From the recorder's last line: "recorded N messages ... (X s CPU)"."""
    log = (run_dir / "logs" / "recorder-0.log").read_text()
    cpu_s = float(re.findall(r"\(([0-9.]+) s CPU", log)[-1])
    finished = next(e for e in report["events"] if e["type"] == "run_finished")
    return cpu_s / finished["steps"] * 1e6


def run() -> list[Figure]:
    plain, recorded, sizes, cpu = [], [], [], []
    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        lockstep = ("--uavs", str(UAVS), "--episodes", EPISODES, "--map", "perfect")
        for repeat in range(REPEATS):
            plain.append(up_report(tmp / f"plain{repeat}", *lockstep)["steps_per_second"])
            recording = tmp / f"recorded{repeat}.mcap"
            report = up_report(tmp / f"recorded{repeat}", *lockstep, "--record", str(recording))
            recorded.append(report["steps_per_second"])
            sizes.append(_kib_per_uav_minute(recording, report))
            cpu.append(_recorder_cpu_per_step_us(tmp / f"recorded{repeat}", report))
        # Simulated time 20x wall time; the cloud detects the jammer set 10 s in and
        # publishes corrected maps (each a few hundred KiB of weights).
        online = tmp / "online.mcap"
        report = up_report(tmp / "online", "--uavs", str(UAVS), "--realtime", "--rate", "20",
                     "--duration", "30", "--no-jammer", "--swap-jammer-at", "10",
                     "--map", "online", "--record", str(online))
        online_size = _kib_per_uav_minute(online, report)
        maps = sum(e["type"] == "sinr_weights_published" for e in report["events"])
    cpu_per_step = median(cpu)
    return [
        Figure(f"lockstep steps/s, {UAVS} agents, best / median of {REPEATS}", max(plain),
               "steps/s"),
        Figure("  median", median(plain), "steps/s"),
        Figure(f"lockstep steps/s, {UAVS} agents, --record, best / median of {REPEATS}",
               max(recorded), "steps/s"),
        Figure("  median", median(recorded), "steps/s"),
        Figure("step-rate cost of --record, best against best",
               100 * (1 - max(recorded) / max(plain)), "%", 5, True),
        Figure("step-rate cost of --record, median against median",
               100 * (1 - median(recorded) / median(plain)), "%", 5, True),
        Figure(f"recorder CPU per lockstep step ({2 * UAVS + 1} messages), median",
               cpu_per_step, "us"),
        Figure(f"recorder CPU at {max(plain):.0f} steps/s, share of one core",
               cpu_per_step * max(plain) / 1e4, "%"),
        Figure("MCAP size, lockstep, true map", min(sizes), "KiB/UAV-min"),
        Figure(f"MCAP size, realtime, online map ({maps} maps published)", online_size,
               "KiB/UAV-min"),
    ]
