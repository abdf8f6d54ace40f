"""Events of a run (messages dumped as JSON) as lines for people: the supervisor's live output
and summary and the console's log write the same line."""

from __future__ import annotations

from typing import Any

from shared.jammer_messages import (
    JammerEstimate,
    JammerInfo,
    describe_count,
    describe_estimate,
    describe_jammers,
    recorded_one_jammer,
)


def describe_event(event: dict[str, Any]) -> str | None:
    """One line for people about an event (a message dumped as JSON); None for the outcomes
    and the end of the run, which the summary counts instead."""
    kind = event["type"]
    if kind == "jammer_changed":
        # A report written when a world had one jammer names it alone.
        listed = recorded_one_jammer(event, "jammer", "jammers").get("jammers") or []
        jammers = [JammerInfo.model_validate(jammer) for jammer in listed]
        return (f"{describe_jammers(jammers)} (episode {event.get('episode')}, step "
                f"{event.get('step')})")
    if kind == "change_detected":
        return (f"change detected: map v{event['version']} right on "
                f"{event['accuracy']:.0%} of recent uploads")
    if kind == "jammer_estimated":
        estimate = JammerEstimate(**event["estimate"])
        return f"map v{estimate.map_version}, jammer at {describe_estimate(estimate)}"
    if kind == "sinr_weights_published":
        accuracy = event.get("accuracy")
        what = "provisional SINR map" if event.get("provisional") else "SINR map"
        counted = event.get("jammers_counted")
        return f"{what} v{event['version']} published" + (
            f", {describe_count(counted)}, not placed yet"
            if event.get("provisional") and counted is not None else "") + (
            "" if accuracy is None else f" (held-out accuracy {accuracy:.1%})")
    if kind == "weights_refused":
        version = event["version"] if event.get("version") is not None else "?"
        return (f"agent {event['uav']} refused {event['weights']} weights v{version} "
                f"({event['reason']}); flying on v{event.get('flying_on')}")
    if kind == "retrain_failed":
        return f"retraining map v{event['version']} failed: {event['error']}"
    return None

