"""Faults injected into a running ``jamnav up`` (every role its own OS process): SIGKILL the
cloud, the world or an agent mid-run, then Ctrl-C. The supervisor restarts what died; the
others keep flying, and every measurement the UAVs take reaches the cloud's memory exactly
once."""

from __future__ import annotations

import json
import logging
import os
import signal
import time
from collections import defaultdict

from cloud_service.sinr_memory import RUN_DIR_FILE, SinrMemory
from jamnav.cli import main as jamnav
from shared.measurements import MeasurementSpec
from tests.support import free_endpoint, gone, wait_until
from uav_agent.uploads import RECEIPT_TIMEOUT_S, OutboxFile, outbox_path


def statuses(capsys, endpoint: str) -> list[dict]:
    code = jamnav(["status", "--json", "--endpoint", endpoint])
    out = capsys.readouterr().out
    return json.loads(out) if code == 0 else []


def one(found: list[dict], role: str, ident: str = "0") -> dict | None:
    return next((p for p in found if p["role"] == role and p["id"] == ident and "pid" in p),
                None)


def test_killed_cloud_comes_back_with_its_memory_and_no_measurement_is_lost(
        supervisor, capsys, tmp_path):
    endpoint, run_dir = free_endpoint(), tmp_path / "run"
    process = supervisor("--uavs", "3", "--realtime", "--rate", "20", "--duration", "120",
                         "--map", "perfect", "--no-figures", "--endpoint", endpoint,
                         "--run-dir", str(run_dir))

    def stored() -> int:
        cloud = one(statuses(capsys, endpoint), "cloud")
        return cloud["details"]["stored"] if cloud else 0

    wait_until(lambda: stored() >= 50, 90, "measurements in the cloud's memory")
    found = statuses(capsys, endpoint)
    cloud = one(found, "cloud")
    decisions = {p["id"]: p["details"]["decisions"] for p in found if p["role"] == "agent"}
    # First the cloud freezes for longer than an upload waits for its receipt (uploads time
    # out, are sent again, and the frozen cloud later takes both copies), then it dies.
    os.kill(cloud["pid"], signal.SIGSTOP)
    time.sleep(RECEIPT_TIMEOUT_S + 1.5)
    # Frozen, its token is still live: status says it does not answer, not that it is well.
    frozen = next(p for p in statuses(capsys, endpoint) if p["role"] == "cloud")
    assert frozen == {"role": "cloud", "id": "0", "answering": False}
    os.kill(cloud["pid"], signal.SIGCONT)
    time.sleep(1.0)
    os.kill(cloud["pid"], signal.SIGKILL)
    restarted = wait_until(lambda: (c := one(statuses(capsys, endpoint), "cloud"))
                           and c["pid"] != cloud["pid"] and c, 60, "the cloud restarted")
    # It reloaded what it had stored before it was frozen and killed; meanwhile the agents
    # flew on (3 UAVs at 20 steps/s for over 8 s: up to 480 decisions, fewer as UAVs that
    # ended their mission wait for the next episode).
    assert restarted["details"]["stored"] >= cloud["details"]["stored"]
    after = {p["id"]: p["details"]["decisions"] for p in statuses(capsys, endpoint)
             if p["role"] == "agent"}
    assert all(after[ident] > before for ident, before in decisions.items())
    assert sum(after.values()) - sum(decisions.values()) > 150
    # Uploads refused while the cloud was away are sent again once it answers.
    wait_until(lambda: stored() > restarted["details"]["stored"], 60,
               "uploads stored by the restarted cloud")
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=120)
    assert process.returncode == 0, err[-2000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["restarts"] == {"router": 0, "world": 0, "cloud": 1, "agent": 0}
    counts = report["measurements"]
    # Their uploads found no cloud for a while.
    assert counts["upload_failures"] > 0
    assert counts["taken"] > 3 * cloud["details"]["stored"] // 3
    # Exactly once: the memory's ids are unique, and it holds one row per measurement taken.
    assert counts["buffered"] == counts["overflowed"] == counts["refused"] == 0
    assert counts["in_memory"] == counts["taken"] == counts["acknowledged"]
    assert all(gone(p["pid"]) for p in report["processes"])


def test_killed_world_is_restarted_and_the_agents_fly_its_episodes(supervisor, capsys,
                                                                   tmp_path):
    endpoint, run_dir = free_endpoint(), tmp_path / "run"
    process = supervisor("--uavs", "2", "--realtime", "--rate", "25", "--episodes", "4",
                         "--map", "perfect", "--no-figures", "--endpoint", endpoint,
                         "--run-dir", str(run_dir))
    world = wait_until(lambda: (w := one(statuses(capsys, endpoint), "world"))
                       and w["episode"] >= 1 and w, 120, "the first episode done")
    agents_before = {p["id"]: p["details"]["decisions"] for p in statuses(capsys, endpoint)
                     if p["role"] == "agent"}
    os.kill(world["pid"], signal.SIGKILL)
    out, err = process.communicate(timeout=180)
    assert process.returncode == 0, err[-2000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["restarts"] == {"router": 0, "world": 1, "cloud": 0, "agent": 0}
    # The interrupted episode is flown again by the new world: four complete episodes.
    assert report["episodes"] == 4 and len(report["outcomes"]) == 4
    assert all(len(row) == 2 for row in report["outcomes"])
    # The same agent processes flew on after the restart.
    for ident, before in agents_before.items():
        assert report["agents"][ident]["decisions"] > before
    # The episode flown again is new data, not a repeat of what the UAVs measured before.
    counts = report["measurements"]
    assert counts["in_memory"] == counts["taken"] > 0 and counts["duplicates"] == 0
    assert all(gone(p["pid"]) for p in report["processes"])


def test_a_killed_agent_leaves_its_outbox_to_the_next_and_ctrl_c_stores_everything(
        supervisor, capsys, scenario, tmp_path):
    endpoint, run_dir = free_endpoint(), tmp_path / "run"
    process = supervisor("--uavs", "2", "--realtime", "--rate", "20", "--duration", "300",
                         "--map", "perfect", "--no-figures", "--endpoint", endpoint,
                         "--run-dir", str(run_dir))
    wait_until(lambda: (c := one(statuses(capsys, endpoint), "cloud"))
               and c["details"]["stored"] >= 50, 90, "measurements in the cloud's memory")
    found = statuses(capsys, endpoint)
    cloud, agent = one(found, "cloud"), one(found, "agent", "1")
    # No receipts while the cloud is frozen, so agent 1's outbox fills; frozen in turn, its
    # file shows what it holds, and it dies with it.
    os.kill(cloud["pid"], signal.SIGSTOP)
    time.sleep(2.0)
    os.kill(agent["pid"], signal.SIGSTOP)
    left_by_dead, left = OutboxFile(outbox_path(run_dir / "outbox", 1),
                                    logging.getLogger("test-faults")).load()
    os.kill(agent["pid"], signal.SIGKILL)
    os.kill(cloud["pid"], signal.SIGCONT)
    assert len(left) > 20
    successor = wait_until(lambda: (a := one(statuses(capsys, endpoint), "agent", "1"))
                           and a["pid"] != agent["pid"] and a["details"]["decisions"] > 0
                           and a, 60, "agent 1 restarted and flying")
    assert successor["details"]["measurements_taken"] >= left_by_dead.taken

    # Ctrl-C while the UAVs fly, their outboxes holding what they took since the last upload.
    process.send_signal(signal.SIGINT)
    out, err = process.communicate(timeout=120)
    assert process.returncode == 0, err[-2000:]
    report = json.loads((run_dir / "report.json").read_text())
    assert report["stopped_by"] == "signal"
    assert report["restarts"] == {"router": 0, "world": 0, "cloud": 0, "agent": 1}
    assert report["restarted"] == {"agent-1": 1}
    # How long UAV 1 flew on alone depends on how fast its successor came: only counted.
    assert isinstance(report["unattended_steps"], int)
    counts = report["measurements"]
    assert counts["buffered"] == counts["overflowed"] == counts["refused"] == 0
    assert counts["in_memory"] == counts["taken"] == counts["acknowledged"]
    assert "still buffered" not in out
    assert f"{counts['taken']} taken, {counts['taken']} in the cloud's memory" in out
    with SinrMemory(run_dir / RUN_DIR_FILE, MeasurementSpec.of(scenario)) as memory:
        ids = memory.recent(memory.count()).ids
    assert len(ids) == len(set(ids)) == counts["taken"]
    assert {ident for _, (ident, *_) in left} <= set(ids)
    # Ids are <uav>-<agent process>-<count>: every count each agent process wrote is there.
    counted = defaultdict(set)
    for ident in ids:
        uav, nonce, count = ident.split("-")
        counted[uav, nonce].add(int(count))
    assert sorted(uav for uav, _ in counted) == ["0", "1", "1"]
    assert all(counts_seen == set(range(len(counts_seen))) for counts_seen in counted.values())
    assert all(gone(p["pid"]) for p in report["processes"])
