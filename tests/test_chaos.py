"""``jamnav chaos`` for two minutes against the real processes: the world, the cloud, an agent
and the router each killed and each frozen, and the ledger holds (every measurement stored
once, every episode booked once, no process left, bounded memory growth). On the run's own
files, the measurement check then fails as soon as measurements go missing."""

from __future__ import annotations

import json
import os
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import zenoh

from cloud_service.sinr_memory import RUN_DIR_FILE
from jamnav.chaos import KINDS, QUIET_S, ROLES, episode_check, fault_schedule, measurement_check
from jamnav.cli import main as jamnav
from shared import bus
from tests.support import free_endpoint, wait_until

ROOT = Path(__file__).resolve().parent.parent
EVERY_PAIR = {(role, kind) for role in ROLES for kind in KINDS}


def test_every_eight_faults_hit_every_role_both_ways_at_seeded_times():
    faults = fault_schedule(7, 1800, (10, 30), (2, 6), 3)
    assert faults == fault_schedule(7, 1800, (10, 30), (2, 6), 3)
    assert len(faults) >= 1800 // 30 - 1
    for deck in range(0, len(faults) - 7, 8):
        assert {(f.role, f.kind) for f in faults[deck:deck + 8]} == EVERY_PAIR
    times = np.array([0.0] + [f.at for f in faults])
    assert ((np.diff(times) >= 9.9) & (np.diff(times) <= 30.1)).all()
    assert faults[-1].at <= 1800 - QUIET_S
    assert {f.uav for f in faults if f.role == "agent"} == {0, 1, 2}
    assert all(2 <= f.freeze_s <= 6 for f in faults)


def test_the_episode_check_finds_gaps_repeats_and_strays():
    assert episode_check([0, 1, 2], 3).ok
    check = episode_check([0, 2, 2, 5], 4)
    assert not check.ok
    assert (check.details["gaps"], check.details["repeats"], check.details["beyond"]) == (
        [1, 3], [2], [5])
    assert not episode_check([0], None).ok


def test_bad_arguments_are_one_line_before_anything_starts(capsys, tmp_path):
    (tmp_path / "used").mkdir()
    (tmp_path / "used" / "report.json").write_text("{}")
    for argv, says in (
            (["--duration", "30"], "--duration must be at least 50"),
            (["--duration", "100", "--interval", "10"], "expected 2 finite comma"),
            (["--duration", "100", "--interval", "5,3"], "0 < MIN <= MAX"),
            (["--duration", "100", "--freeze", "2,12"], "a freeze ends before the next"),
            (["--duration", "100", "--rate", "0"], "--rate must be a finite number above 0"),
            (["--duration", "100", "--run-dir", str(tmp_path / "used")], "not empty"),
            (["--duration", "100", "--endpoint", "tcp/nowhere"], "expected PROTOCOL/HOST:PORT")):
        assert jamnav(["chaos", *argv]) == 2
        err = capsys.readouterr().err
        assert says in err and err.count("\n") == 1, (argv, err)


def test_eighty_five_seconds_of_kills_and_freezes_lose_nothing(scenario, tmp_path):
    run_dir = tmp_path / "chaos"
    done = subprocess.run(
        [sys.executable, "-m", "jamnav.cli", "chaos", "--duration", "85", "--interval",
         "6,8", "--freeze", "2,5", "--seed", "3", "--uavs", "3", "--rate", "10",
         "--endpoint", free_endpoint(), "--run-dir", str(run_dir)],
        cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True, text=True,
        timeout=400)
    assert done.returncode == 0, done.stderr[-3000:]
    ledger = json.loads((run_dir / "ledger.json").read_text())
    dealt = [f for f in ledger["faults"] if not f["skipped"]]
    # Eight faults at most 8 s apart fit in the 65 s before the quiet end: a whole deck.
    assert {(f["role"], f["kind"]) for f in dealt} == EVERY_PAIR
    assert [c["name"] for c in ledger["checks"] if c["ok"]] == [
        "run", "measurements", "episodes", "processes", "memory"]
    assert "ledger: all checks pass" in done.stdout
    assert done.stderr.count("chaos: kill") + done.stderr.count("chaos: freeze") == len(dealt)
    counts = next(c for c in ledger["checks"] if c["name"] == "measurements")["details"]
    assert counts["in_memory"] > 1000

    # Measurements lost: the last one stored of UAV 0, and one amid UAV 1's (a gap).
    with sqlite3.connect(run_dir / RUN_DIR_FILE) as db:
        for source, order, offset in (("uav-0", "DESC", 0), ("uav-1", "ASC", 10)):
            db.execute("DELETE FROM measurements WHERE seq = (SELECT seq FROM measurements "
                       f"WHERE source = ? ORDER BY seq {order} LIMIT 1 OFFSET ?)",
                       (source, offset))
    check = measurement_check(run_dir, scenario, 3)
    assert not check.ok
    assert "uav-0: 1 of" in check.summary and "uav-1: 1 of" in check.summary
    assert "uav-1: 1 missing between stored ones" in check.summary
    assert check.details["in_memory"] == counts["in_memory"] - 2


def test_outcomes_put_while_the_router_restarts_reach_the_supervisor_once():
    """What the chaos found first: an outcome put while the router was down reached no one,
    and its episode was missing from the run. The world now keeps its outcomes and the
    supervisor fetches what it missed."""
    endpoint, key = free_endpoint(), "test/event/uav_outcomes"

    def router() -> subprocess.Popen:
        return subprocess.Popen([sys.executable, "-m", "jamnav.cli", "router", "--endpoint",
                                 endpoint], cwd=ROOT, env=dict(os.environ, PYTHONPATH=str(ROOT)),
                                stderr=subprocess.DEVNULL)

    routers = [router()]
    got: list[int] = []
    try:
        with bus.open_session("client", endpoint) as world, \
                bus.open_session("client", endpoint) as supervisor:
            heard = bus.recovering_subscriber(supervisor, "test/event/*", lambda sample: (
                got.append(int(sample.payload.to_bytes()))))
            outcomes = bus.recoverable_publisher(world, key, 100)
            wait_until(lambda: outcomes.put(b"0") or got, 10, "the first outcome")
            routers[0].kill()
            routers[0].wait()
            for episode in (1, 2, 3):  # while no router runs
                outcomes.put(str(episode).encode())
            routers.append(router())
            wait_until(lambda: set(got) == {0, 1, 2, 3}, 30, "the outcomes put meanwhile")
            outcomes.put(b"4")
            wait_until(lambda: 4 in got, 10, "the next outcome")
            time.sleep(2 * bus.RECOVERY_HEARTBEAT_S)  # room for a repeat, if any came
            del heard
    finally:
        for process in routers:
            process.kill()
            process.wait()
    assert sorted(set(got)) == [0, 1, 2, 3, 4]
    assert [n for n in got if n] == [1, 2, 3, 4]


def test_events_put_at_once_by_several_processes_all_reach_the_supervisor():
    """What the fuzzing found: the router stamped every event with its clock, and the
    supervisor's subscriber dropped an event stamped before one it had already passed on, as
    happens when two processes publish at once. Three publishers here, as the world, the cloud
    and an agent, each with its own link to the router."""
    endpoint, puts = free_endpoint(), 10_000
    heard = [0]
    with bus.open_session("router", endpoint) as _, \
            bus.open_session("client", endpoint) as supervisor:
        subscriber = bus.recovering_subscriber(
            supervisor, "test/event/*", lambda sample: heard.__setitem__(0, heard[0] + 1))
        publishers = [bus.open_session("client", endpoint) for _ in range(3)]
        try:
            time.sleep(bus.MATCH_SETTLE_S * 10)  # the subscription reaches every publisher

            def flood(session, kind: int) -> None:
                for _ in range(puts):
                    session.put(f"test/event/kind{kind}", b"event",
                                congestion_control=zenoh.CongestionControl.BLOCK)

            threads = [threading.Thread(target=flood, args=(session, kind))
                       for kind, session in enumerate(publishers)]
            for thread in threads:
                thread.start()
            for thread in threads:
                thread.join()
            deadline = time.monotonic() + 30
            while heard[0] < puts * len(publishers) and time.monotonic() < deadline:
                time.sleep(0.1)
            time.sleep(0.5)  # room for a repeat, if any came
        finally:
            for session in publishers:
                session.close()
        del subscriber
    assert heard[0] == puts * len(publishers)
