"""``jamnav chaos``: the system of ``jamnav up`` under faults, then a ledger of what must have
come through them.

While the system flies, a fault every 10-30 s (seeded) kills one process (SIGKILL) or freezes
it (SIGSTOP, then SIGCONT a few seconds later): the world, the cloud, an agent or the router.
Role and kind are dealt from a shuffled deck of every (role, kind) pair, dealt afresh once
used up, so that every eight faults hit each role both ways. The supervisor restarts what was
killed. The world flies in real time: faults are about time (a frozen process misses steps,
queries time out), and a lockstep world would only wait for a frozen agent. No fault comes in
the last ``QUIET_S`` seconds, so that restarted processes settle and outboxes drain.

At the end the supervisor stops everything and the ledger checks, as a table and as
``ledger.json`` in the run directory:

- run: the run ended on time, and the supervisor restarted each killed process once (and
  nothing else: no process died by itself);
- measurements: every measurement taken is in the cloud's memory exactly once. Each UAV's
  outbox file holds its count of measurements taken (across all its agents) and what has no
  receipt; the memory's ids are ``<uav>-<nonce>-<n>``, numbered 0, 1, ... by each agent
  process (its nonce), so a gap in a process's numbers or a count below the number taken is
  a loss, wherever it happened;
- episodes: the outcomes booked are those of episodes 0 .. N-1 of the world, each once;
- processes: every process launched is gone;
- memory: no process grew its resident memory by more than its role's ``RSS_GROWTH_MIB``
  between a sample before the first fault and one before the stop (a restarted process is
  compared with the one it replaced). Each bound is about twice the largest growth seen in
  2-5 minute runs, clean and under chaos, in steps of 64 MiB: world +2 and router +20 MiB
  (they hold no data), an agent +93 MiB (a raster for each new map), the cloud +265 MiB (its
  retraining after a detected change; it settles ~150 MiB above its start). A leak shows
  over a soak as steady growth past these; the samples every ``RESIDENT_EVERY_S`` are in the
  ledger for a closer look.
"""

from __future__ import annotations

import json
import logging
import random
import signal
import sys
import threading
import time
from collections import Counter, defaultdict
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, TextIO

import zenoh

from cloud_service.sinr_memory import RUN_DIR_FILE, SinrMemory
from jamnav.routers import check_endpoint_free
from jamnav.run_report import summary_table
from jamnav.supervisor import OUTBOX_DIR, Child, Supervisor, UpConfig
from shared.measurements import MeasurementSpec
from shared.process_status import ProcessStatus
from shared.resources import resident_mib
from shared.scenario import Scenario
from uav_agent.uploads import OutboxFile, outbox_path

ROLES = ("world", "cloud", "agent", "router")
KINDS = ("kill", "freeze")
QUIET_S = 20.0
RSS_GROWTH_MIB = {"world": 64, "router": 64, "agent": 192, "cloud": 576}
RESIDENT_EVERY_S = 10.0  # resident memory sampled this often, for the ledger's record
LEDGER_FILE = "ledger.json"


@dataclass(frozen=True)
class Fault:
    at: float  # seconds after the world's first step
    role: str
    kind: str
    uav: int  # the agent hit, when the role is "agent"
    freeze_s: float  # how long a frozen process stays frozen


def fault_schedule(seed: int, duration: float, interval: tuple[float, float],
                   freeze: tuple[float, float], uavs: int) -> list[Fault]:
    """Faults ``interval`` seconds apart until ``QUIET_S`` before the end of ``duration``,
    role and kind dealt from a shuffled deck of every pair."""
    rng = random.Random(seed)
    faults: list[Fault] = []
    deck: list[tuple[str, str]] = []
    at = 0.0
    while (at := at + rng.uniform(*interval)) <= duration - QUIET_S:
        if not deck:
            deck = [(role, kind) for role in ROLES for kind in KINDS]
            rng.shuffle(deck)
        role, kind = deck.pop()
        faults.append(Fault(round(at, 1), role, kind, rng.randrange(uavs),
                            round(rng.uniform(*freeze), 1)))
    return faults


# -- processes, from /proc ------------------------------------------------------------------------
def _stat_fields(pid: int) -> list[str] | None:
    """The fields of /proc/PID/stat after the command name (state first); None if gone."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except (FileNotFoundError, ProcessLookupError):
        return None


def started_at(pid: int) -> int | None:
    """When the process started, in clock ticks since boot: tells it from a later process
    that got the same pid."""
    fields = _stat_fields(pid)
    return None if fields is None else int(fields[19])


def still_running(pid: int, started: int | None) -> bool:
    """The process launched as ``pid`` at ``started`` is still there (a zombie is not)."""
    fields = _stat_fields(pid)
    return fields is not None and fields[0] != "Z" and (
        started is None or int(fields[19]) == started)


# -- the run ------------------------------------------------------------------------------------
class ChaosSupervisor(Supervisor):
    """The supervisor of ``jamnav up`` with a thread that deals the faults, and what the ledger
    needs of the run: when each process started, resident memory, the final statuses."""

    def __init__(self, config: UpConfig, scenario: Scenario, faults: list[Fault],
                 stream: TextIO = sys.stderr):
        super().__init__(config, scenario, stream)
        self.faults = faults
        self.applied: list[dict[str, Any]] = []
        self.births: dict[int, int | None] = {}
        self.resident: dict[str, dict[str, Any]] = {}  # "start" and "end": name -> pid, MiB
        self.resident_series: list[dict[str, float | None]] = []  # "t" and name -> MiB
        self.final_statuses: list[ProcessStatus] = []
        self._over = threading.Event()
        self._helpers = [threading.Thread(target=target, name=f"chaos{target.__name__}",
                                          daemon=True) for target in (self._deal, self._watch)]

    def _launch(self, child: Child) -> None:
        super()._launch(child)
        self.births[child.process.pid] = started_at(child.process.pid)

    def run(self) -> dict[str, Any]:
        for helper in self._helpers:
            helper.start()
        try:
            return super().run()
        finally:
            self._end_helpers()

    def _end_helpers(self) -> None:
        """No more faults or samples; a frozen process is thawed."""
        self._over.set()
        for helper in self._helpers:
            helper.join()

    def _stop_in_order(self, session: zenoh.Session) -> list[ProcessStatus]:
        self._end_helpers()  # before any process is asked to stop
        self.resident["end"] = self._resident()
        self.final_statuses = super()._stop_in_order(session)
        return self.final_statuses

    def _resident(self) -> dict[str, Any]:
        return {child.name: {"role": child.role, "pid": child.process.pid,
                             "mib": resident_mib(child.process.pid)}
                for child in list(self.children.values()) if child.role in RSS_GROWTH_MIB}

    def _watch(self) -> None:
        while not self._over.wait(RESIDENT_EVERY_S):
            if self.first_step is not None:
                self.resident_series.append({
                    "t": round(time.monotonic() - self.first_step, 1),
                    **{name: sample["mib"] for name, sample in self._resident().items()}})

    def _deal(self) -> None:
        while self.first_step is None:
            if self._over.wait(0.1):
                return
        for fault in self.faults:
            if self._over.wait(max(0.0, self.first_step + fault.at - time.monotonic())):
                return
            if "start" not in self.resident:
                self.resident["start"] = self._resident()
            self._strike(fault)

    def _strike(self, fault: Fault) -> None:
        child = next(c for c in list(self.children.values()) if c.role == fault.role and (
            c.ident == (fault.uav if fault.role == "agent" else 0)))
        process = child.process
        record = {**asdict(fault), "target": child.name, "pid": process.pid}
        if process.poll() is not None:  # dead, not restarted yet
            self._say(f"chaos: {child.name} is down already; {fault.kind} skipped")
            self.applied.append({**record, "skipped": True})
            return
        self.applied.append({**record, "skipped": False})
        if fault.kind == "kill":
            self._say(f"chaos: kill {child.name} (pid {process.pid})")
            process.send_signal(signal.SIGKILL)
            return
        self._say(f"chaos: freeze {child.name} (pid {process.pid}) for {fault.freeze_s:g} s")
        process.send_signal(signal.SIGSTOP)
        try:
            self._over.wait(fault.freeze_s)
        finally:
            process.send_signal(signal.SIGCONT)

    # -- the ledger ---------------------------------------------------------------------------
    def ledger(self, report: dict[str, Any]) -> list[Check]:
        world = next((s for s in self.final_statuses if s.role == "world"), None)
        booked = [e["episode"] for e in self.events if e["type"] == "uav_outcomes"]
        return [
            run_check(report, self.applied, self.config.duration),
            measurement_check(self.config.run_dir, self.scenario, self.config.uavs),
            episode_check(booked, None if world is None else world.episode),
            process_check(report["processes"], self.births),
            resident_check(self.resident.get("start"), self.resident.get("end"),
                           self.resident_series),
        ]


@dataclass
class Check:
    name: str
    ok: bool
    summary: str  # one line
    details: dict[str, Any] = field(default_factory=dict)


def run_check(report: dict[str, Any], applied: list[dict[str, Any]], duration: float
              ) -> Check:
    kills = Counter(f["role"] for f in applied if f["kind"] == "kill" and not f["skipped"])
    restarts = report["restarts"]
    kinds = Counter(f["kind"] for f in applied if not f["skipped"])
    text = (f"{len(applied)} faults ({kinds['kill']} kills, {kinds['freeze']} freezes) in "
            f"{duration:g} s; restarts " + ", ".join(f"{r} {n}" for r, n in restarts.items()))
    details = {"stopped_by": report["stopped_by"], "kills": dict(kills), "restarts": restarts}
    if report["stopped_by"] != "end":
        return Check("run", False, f"the run was stopped by {report['stopped_by']}, not by its "
                     "end", details)
    wrong = [f"{role} restarted {restarts.get(role, 0)} times, killed {kills[role]} times"
             for role in ROLES if restarts.get(role, 0) != kills[role]]
    if wrong:
        return Check("run", False, "; ".join(wrong), details)
    return Check("run", True, text, details)


def measurement_check(run_dir: Path, scenario: Scenario, uavs: int) -> Check:
    """Outbox files against the cloud's memory: see the module's docstring."""
    log = logging.getLogger("chaos")
    with SinrMemory(run_dir / RUN_DIR_FILE, MeasurementSpec.of(scenario)) as memory:
        full = memory.count() >= memory.capacity
        stored = memory.recent(memory.count())
    by_source: dict[str, list[str]] = defaultdict(list)
    for ident, source in zip(stored.ids, stored.sources, strict=True):
        by_source[source].append(ident)
    per_uav, problems = {}, []
    for uav in range(uavs):
        ledger, held = OutboxFile(outbox_path(run_dir / OUTBOX_DIR, uav), log).load()
        ids = by_source.pop(f"uav-{uav}", [])
        counts = uav_counts(ledger.taken, ids, len(held))
        counts.update(overflowed=ledger.overflowed, refused=ledger.refused)
        per_uav[f"uav-{uav}"] = counts
        problems += [f"uav-{uav}: {problem}" for problem in uav_problems(counts)]
    foreign = sum(len(ids) for ids in by_source.values())
    if foreign:
        problems.append(f"{foreign} measurements in the memory from no UAV of this run "
                        f"({', '.join(sorted(by_source))})")
    if full:
        problems.append(f"the memory is full ({len(stored)} rows): it dropped its oldest, so "
                        "the ledger cannot tell; shorten the run or slow it (--rate)")
    taken = sum(c["taken"] for c in per_uav.values())
    details = {"uavs": per_uav, "in_memory": len(stored)}
    if problems:
        return Check("measurements", False, "; ".join(problems), details)
    return Check("measurements", True, f"{taken} taken, {len(stored)} in the cloud's memory, "
                 "each once", details)


def uav_counts(taken: int, ids: list[str], held: int) -> dict[str, int]:
    """One UAV's measurements: ``taken`` (its outbox file's count), the memory's ``ids`` of
    it, and ``held`` (still in its outbox). Numbers missing between an agent process's first
    and last stored measurement are ``gaps``."""
    numbers: dict[str, set[int]] = defaultdict(set)
    malformed = 0
    for ident in ids:
        _, _, number = ident.rpartition("-")
        if number.isdigit():
            numbers[ident.rpartition("-")[0]].add(int(number))
        else:
            malformed += 1
    gaps = sum(max(found) + 1 - len(found) for found in numbers.values())
    return {"taken": taken, "stored": len(set(ids)), "repeated": len(ids) - len(set(ids)),
            "gaps": gaps, "held": held, "malformed": malformed, "agents": len(numbers)}


def uav_problems(counts: dict[str, int]) -> list[str]:
    problems = []
    if counts["stored"] < counts["taken"]:
        problems.append(f"{counts['taken'] - counts['stored']} of {counts['taken']} "
                        "measurements taken are not in the cloud's memory")
    elif counts["stored"] > counts["taken"]:
        problems.append(f"the memory holds {counts['stored']}, more than the "
                        f"{counts['taken']} taken")
    for name, what in (("gaps", "missing between stored ones"), ("repeated", "stored twice"),
                       ("held", "still in the outbox"), ("overflowed", "dropped from a full "
                       "outbox"), ("refused", "refused by the cloud"),
                       ("malformed", "stored under a malformed id")):
        if counts[name]:
            problems.append(f"{counts[name]} {what}")
    return problems


def episode_check(booked: list[int], finished: int | None) -> Check:
    """``booked``: the episode of every outcome booked, in order; ``finished``: the world's
    episode number at the end (episodes below it are over)."""
    if finished is None:
        return Check("episodes", False, "the world did not answer at the end", {})
    times = Counter(booked)
    gaps = sorted(set(range(finished)) - times.keys())
    repeats = sorted(k for k, n in times.items() if n > 1)
    beyond = sorted(k for k in times if not 0 <= k < finished)
    details = {"world_episodes": finished, "booked": len(booked), "gaps": gaps,
               "repeats": repeats, "beyond": beyond}
    problems = [f"{what} {values}" for what, values in (
        ("no outcome for episodes", gaps), ("outcomes booked twice for episodes", repeats),
        ("outcomes for episodes the world did not end", beyond)) if values]
    if problems:
        return Check("episodes", False, "; ".join(problems), details)
    return Check("episodes", True, f"{finished} episodes, each booked once", details)


def process_check(launched: list[dict[str, Any]], births: dict[int, int | None]) -> Check:
    left = [p for p in launched if still_running(p["pid"], births.get(p["pid"]))]
    details = {"launched": len(launched), "left": left}
    if left:
        return Check("processes", False, f"{len(left)} of {len(launched)} processes launched "
                     "are still running: " + ", ".join(
                         f"{p['role']}-{p['id']} (pid {p['pid']})" for p in left), details)
    return Check("processes", True, f"{len(launched)} launched, none left", details)


def resident_check(start: dict[str, Any] | None, end: dict[str, Any] | None,
                   series: list[dict[str, float | None]]) -> Check:
    if start is None or end is None:
        return Check("memory", False, "resident memory was not sampled at both ends (no "
                     "fault was dealt?)", {"start": start, "end": end, "series": series})
    growth = {name: round(end[name]["mib"] - start[name]["mib"], 1) for name in start
              if start[name]["mib"] is not None and end.get(name, {}).get("mib") is not None}
    details = {"bound_mib": RSS_GROWTH_MIB, "growth_mib": growth, "start": start, "end": end,
               "series": series}
    unsampled = sorted(set(start) - growth.keys())
    if unsampled:
        return Check("memory", False, f"no resident memory of {', '.join(unsampled)} at both "
                     "ends", details)
    bounds = {name: RSS_GROWTH_MIB[start[name]["role"]] for name in growth}
    worst = max(growth, key=lambda name: growth[name] / bounds[name])
    over = [f"{name} +{mib:g} MiB (bound {bounds[name]})" for name, mib in growth.items()
            if mib > bounds[name]]
    if over:
        return Check("memory", False, "resident memory grew too much: " + ", ".join(over),
                     details)
    return Check("memory", True, f"nearest its bound: {worst} {growth[worst]:+g} MiB (bound "
                 f"{bounds[worst]} MiB)", details)


def ledger_table(checks: list[Check]) -> str:
    failed = sum(not c.ok for c in checks)
    rows = [f"ledger: {f'{failed} of {len(checks)} checks fail' if failed else 'all checks pass'}"]
    rows += [f"  {c.name:<13} {'ok' if c.ok else 'FAIL':<5} {c.summary}" for c in checks]
    return "\n".join(rows)


def chaos(config: UpConfig, scenario: Scenario, faults: list[Fault]) -> int:
    """Run, deal the faults, stop, write the report and the ledger; 1 if a check fails."""
    check_endpoint_free(config.endpoint)
    supervisor = ChaosSupervisor(config, scenario, faults)
    report = supervisor.run()
    (config.run_dir / "report.json").write_text(json.dumps(report, indent=2) + "\n",
                                                encoding="utf-8")
    print(summary_table(report))
    checks = supervisor.ledger(report)
    ledger = {"ok": all(c.ok for c in checks), "faults": supervisor.applied,
              "checks": [asdict(c) for c in checks]}
    path = config.run_dir / LEDGER_FILE
    path.write_text(json.dumps(ledger, indent=2) + "\n", encoding="utf-8")
    print(ledger_table(checks))
    print(f"report: {config.run_dir / 'report.json'}, ledger: {path}")
    failed = [c for c in checks if not c.ok]
    if failed:
        print("jamnav: chaos: " + "; ".join(f"{c.name}: {c.summary}" for c in failed),
              file=sys.stderr)
        return 1
    return 0
