"""The report of a ``jamnav up`` run, built after it from what the supervisor followed: the
report JSON (outcomes, rates, restarts, dropped messages, measurement counts, the cloud's
latency), the summary printed for people, and the trajectory figures."""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from jamnav.event_lines import describe_event
from shared.jammer_messages import JammerInfo
from shared.outcomes import FINAL_OUTCOMES
from shared.process_status import ProcessStatus
from shared.shipped import value_net_name

if TYPE_CHECKING:  # the supervisor builds its report with this module
    from jamnav.supervisor import Supervisor


def build_report(supervisor: Supervisor, statuses: list[ProcessStatus]) -> dict[str, Any]:
    """The report JSON of the run ``supervisor`` followed, with the final ``statuses`` of its
    processes."""
    c = supervisor.config
    outcomes = [supervisor.outcomes[k] for k in sorted(supervisor.outcomes)]
    labels = [label for row in outcomes for label in row]
    rates = {f"{o.label}_rate": (labels.count(o.label) / len(labels) if labels else None)
             for o in FINAL_OUTCOMES}
    dropped: Counter = Counter(supervisor.dropped.as_dict())
    for status in statuses:
        dropped.update(status.dropped)
    world = next((s for s in statuses if s.role == "world"), supervisor.world_status)
    details = world.details if world is not None else {}
    restarts = dict.fromkeys(("router", "world", "cloud", "agent"), 0)
    for child in supervisor.children.values():
        restarts[child.role] = restarts.get(child.role, 0) + child.restarts
    return {
        "command": c.command,
        "run_dir": str(c.run_dir),
        "endpoint": c.endpoint,
        "scenario": supervisor.scenario.name,
        "clock": c.clock,
        "map": c.map,
        "uavs": c.uavs,
        "seed": c.seed,
        "secure": c.secure,
        "routers": c.routers,
        "stopped_by": supervisor.stopped_by,
        "processes": supervisor.launched,
        "model": value_net_name(c.model),
        "episodes": len(outcomes),
        "outcomes": outcomes,
        **rates,
        "swap": swap_rates(supervisor.events,
                           dict(zip(sorted(supervisor.outcomes), outcomes, strict=True))),
        "first_step_after_s": None if supervisor.first_step is None
        else supervisor.first_step - supervisor.launched_at,
        "steps_per_second": (supervisor.finished or details).get("steps_per_second"),
        "missed_deadlines": (supervisor.finished or details).get("missed_deadlines"),
        # UAV-steps flown on at the last velocity while their agent was dead or restarting.
        "unattended_steps": details.get("unattended_steps"),
        "events": supervisor.events,
        "restarts": restarts,
        # Which processes, as the live output named them when they died.
        "restarted": {child.name: child.restarts for child in supervisor.children.values()
                      if child.restarts},
        "dropped_messages": dict(dropped),
        "versions": {f"{s.role}-{s.ident}": {"value": s.value_version, "sinr": s.sinr_version}
                     for s in statuses if s.role in ("cloud", "agent")},
        "agents": {s.ident: {k: s.details.get(k) for k in (
            "decisions", "decision_p50_us", "decision_p99_us", "decision_cpu_p99_us",
            "decision_wait_p99_us")}
            for s in statuses if s.role == "agent"},
        "measurements": {**measurement_counts(statuses),
                         "memory_of_earlier_runs": supervisor.memory_existed},
        "cloud_latency": _cloud_latency(supervisor),
    }


def _cloud_latency(supervisor: Supervisor) -> dict[str, Any] | None:
    """What the cloud's work cost in flight: on the lockstep clock the latency the maps flew
    after (the scenario's, or --cloud-latency); in real time each map's delay after the
    detection of its change, in wall seconds and in seconds of flight at the run's pace."""
    c = supervisor.config
    if c.map != "online":
        return None
    if supervisor.cloud_clock:
        return {"clock": "lockstep", "latency_s": supervisor.scenario.online_map.cloud_latency_s
                if c.cloud_latency is None else c.cloud_latency}
    return {"clock": "wall", "maps": map_delays(
        supervisor.events, c.rate * supervisor.scenario.timing.step_s)}


def measurement_counts(statuses: list[ProcessStatus]) -> dict[str, int | None]:
    """Where the UAVs' measurements went: taken by the agents, still in their outboxes,
    dropped from a full outbox, and held by the cloud's memory (which survives a restart of
    the cloud). An agent's outbox file keeps its counts, so a restarted agent carries them on,
    and a rerun in the same run directory counts what earlier runs took, as the memory
    holds what they stored."""
    agents = [s.details for s in statuses if s.role == "agent"]
    cloud = next((s.details for s in statuses if s.role == "cloud"), None)
    counts: dict[str, int | None] = {
        name: sum(int(a.get(f"measurements_{name}") or 0) for a in agents)
        for name in ("taken", "acknowledged", "buffered", "overflowed", "refused",
                     "duplicates")}
    counts["upload_failures"] = sum(int(a.get("upload_failures") or 0) for a in agents)
    counts["in_memory"] = None if cloud is None else cloud.get("stored")
    return counts


def swap_rates(events: list[dict[str, Any]], outcomes: dict[int, list[str]]
               ) -> dict[str, Any] | None:
    """Success before the jammer first changed and from the episode it changed in on (its
    UAVs lived through the change); None without a change."""
    change = next((e for e in events if e["type"] == "jammer_changed"), None)
    if change is None:
        return None

    def success(episodes: list[int]) -> dict[str, Any]:
        labels = [label for k in episodes for label in outcomes[k]]
        return {"episodes": len(episodes),
                "success_rate": labels.count("success") / len(labels) if labels else None}

    return {"episode": change["episode"],
            "before": success([k for k in outcomes if k < change["episode"]]),
            "after": success([k for k in outcomes if k >= change["episode"]])}


def map_delays(events: list[dict[str, Any]], flight_per_wall_s: float) -> list[dict[str, Any]]:
    """Each map published after a detected change: how long after the detection, in wall
    seconds and in seconds of flight."""
    delays, detected = [], None
    for event in events:
        if event["type"] == "change_detected":
            detected = event["t"]
        elif event["type"] == "sinr_weights_published" and detected is not None:
            wall = event["t"] - detected
            delays.append({"version": event["version"], "after_detection_s": round(wall, 3),
                           "flight_s": round(wall * flight_per_wall_s, 3)})
    return delays


def latency_line(latency: dict[str, Any]) -> str | None:
    if latency["clock"] == "lockstep":
        return f"maps fly {latency['latency_s']:g} s of flight after their uploads (lockstep)"
    if not latency["maps"]:
        return None
    first = latency["maps"][0]
    return (f"first map {first['after_detection_s']:.1f} s after the detection (wall), "
            f"{first['flight_s']:.0f} s of flight; {len(latency['maps'])} maps in all")


def agents_line(agents: dict[str, dict[str, Any]]) -> str:
    """The agents at the end, for people: how many, their decisions, the slowest of them
    (the report has every one)."""
    p99 = {ident: a.get("decision_p99_us") for ident, a in agents.items()}
    p99 = {ident: value for ident, value in p99.items() if value is not None}
    decisions = sum(int(a.get("decisions") or 0) for a in agents.values())
    text = f"{len(agents)} reported, {decisions} decisions"
    if p99:
        worst = max(p99, key=p99.get)
        text += (f", decision p99 median {float(np.median(list(p99.values()))):.0f} us, "
                 f"worst {p99[worst]:.0f} us (agent {worst})")
    return text


def _percent(rate: float | None) -> str:
    return "-" if rate is None else f"{rate:.1%}"


def summary_table(report: dict[str, Any]) -> str:
    """The run for people: rounded figures, a word where a number is missing."""
    rows = [f"jamnav up: {report['episodes']} episodes x {report['uavs']} UAVs, "
            f"{report['clock']}, map {report['map']}, value network {report['model']}, "
            f"stopped by {report['stopped_by']}"]
    if report["episodes"] == 0:
        rows.append("  no episode finished")
    else:
        rows.append("  " + ", ".join(f"{o.label} {_percent(report[f'{o.label}_rate'])}"
                                     for o in FINAL_OUTCOMES))
    if (swap := report.get("swap")) is not None:
        rows.append(f"  success        {_percent(swap['before']['success_rate'])} before the "
                    f"jammer changed ({swap['before']['episodes']} episodes), "
                    f"{_percent(swap['after']['success_rate'])} from episode {swap['episode']} "
                    f"on ({swap['after']['episodes']} episodes)")
    if (sps := report["steps_per_second"]) is not None:
        missed = report["missed_deadlines"]
        unattended = report.get("unattended_steps")
        rows.append(f"  pace           {sps:.0f} steps/s"
                    + ("" if missed is None else f", {missed} missed deadlines")
                    + (f", {unattended} UAV-steps without a live agent" if unattended else ""))
    if agents := report.get("agents"):
        rows.append(f"  agents         {agents_line(agents)}")
    restarted = report.get("restarted", {})
    rows.append("  restarts       " + (", ".join(
        f"{name} {'once' if times == 1 else f'{times} times'}"
        for name, times in restarted.items()) or "none"))
    dropped = report["dropped_messages"]
    rows.append("  dropped        " + (", ".join(f"{k} {v}" for k, v in dropped.items())
                                       or "none"))
    rows.append(f"  measurements   {measurement_line(report['measurements'])}")
    if (latency := report.get("cloud_latency")) and (line := latency_line(latency)):
        rows.append(f"  cloud latency  {line}")
    rows += [f"  {line}" for line in map_history(report["events"])]
    return "\n".join(rows)


def measurement_line(m: dict[str, Any]) -> str:
    stored = ("the cloud's memory was not reached" if m["in_memory"] is None
              else f"{m['in_memory']} in the cloud's memory"
              + (" (with earlier runs')" if m["memory_of_earlier_runs"] else ""))
    extra = [f"{m[key]} {what}" for key, what in (
        ("buffered", "still buffered"), ("overflowed", "dropped from full outboxes"),
        ("upload_failures", "uploads retried")) if m.get(key)]
    return ", ".join([f"{m['taken']} taken", stored, *extra])


def map_history(events: list[dict[str, Any]]) -> list[str]:
    """The jammer's changes and the cloud's answers, one line each; a run of refinements (new
    estimate and map, again and again) or of provisional maps shows as its first and last
    line."""
    lines: list[str] = []
    run: list[str] = []
    run_kind = ""

    def close_run() -> None:
        if len(run) > 2:
            between = len(run) - 2
            lines.append(f"  ... {between} {run_kind}{'s' if between > 1 else ''} ...")
        if len(run) > 1:
            lines.append(run[-1])
        run.clear()

    for event in events:
        kind = event["type"]
        provisional = kind == "sinr_weights_published" and event.get("provisional", False)
        if kind == "jammer_estimated" or provisional:
            what = "provisional map" if provisional else "refinement"
            if what != run_kind:
                close_run()
                run_kind = what
            line = describe_event(event)
            if not run:
                lines.append(line)
            run.append(line)
        elif kind in ("jammer_changed", "change_detected"):
            close_run()
            lines.append(describe_event(event))
        elif kind == "sinr_weights_published" and not (run and run_kind == "refinement"):
            close_run()
            lines.append(describe_event(event))
    close_run()
    return lines


def save_trajectory_figures(report: dict[str, Any], supervisor: Supervisor) -> list[str]:
    """Trajectories over the coverage map in force: the last episode before the jammer was
    swapped and the last episode of the run (or just the last one without a swap)."""
    from shared.plots import save_trajectory_figure

    changes = [e for e in report["events"] if e["type"] == "jammer_changed"]
    done = [k for k in sorted(supervisor.outcomes)
            if any(supervisor.trajectories.get(k, [])) and supervisor.destinations.get(k)]
    if not done:
        return []
    panels = []
    if changes:
        swap = changes[0]
        before = [k for k in done if k < swap["episode"]]
        if before:
            panels.append(("before_swap", before[-1], supervisor.initial_jammers))
        panels.append(("after_swap", done[-1], [JammerInfo.model_validate(jammer)
                                                 for jammer in changes[-1]["jammers"]]))
    else:
        panels.append(("last_episode", done[-1], supervisor.initial_jammers))
    written = []
    for label, episode, jammers in panels:
        positions = np.array([p for p in supervisor.trajectories[episode] if p], dtype=float)
        out = Path(report["run_dir"]) / f"trajectories_{label}.png"
        save_trajectory_figure(supervisor.scenario, [(
            f"episode {episode} ({label.replace('_', ' ')})", JammerInfo.params(jammers), positions,
            np.array(supervisor.destinations[episode], dtype=float),
            supervisor.outcomes[episode])], out, dpi=110)
        written.append(str(out))
    return written


def publish_report(report: dict[str, Any], supervisor: Supervisor) -> None:
    """After the run: the trajectory figures and the report JSON written, and on stdout the
    summary and where the run's files are."""
    config = supervisor.config
    if config.figures:
        report["figures"] = save_trajectory_figures(report, supervisor)
    path = config.report or config.run_dir / "report.json"
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=2) + "\n", encoding="utf-8")
    print(summary_table(report))
    print(f"report: {path}" + (f", figures: {', '.join(report['figures'])}"
                               if report.get("figures") else ""))
    if config.record is not None:
        print(f"recording: {config.record}")
    if supervisor.credentials_path is not None:
        print(f"credentials: {supervisor.credentials_path}")
