"""What the console knows of a running system, folded from the messages of the bus: the fleet
(positions, trails, destinations, statuses), the jammers in force (where each is now) and the
cloud's estimate, the SINR map in service, the outcomes so far and a timeline of what
happened. One plain, thread-safe class, so that ``GET /api/state`` and the pushed frames read
one consistent view; the bus and the web server around it only feed it and read it."""

from __future__ import annotations

import json
import threading
from collections import deque
from typing import Any

from jamnav.arguments import UsageError, jammer_command
from jamnav.event_lines import describe_event
from shared.cloud_messages import SinrMap
from shared.events import UavOutcomes
from shared.jammer_messages import JammerCommand, JammerEstimate, JammerPlace, JammersInForce
from shared.outcomes import FINAL_OUTCOMES
from shared.radio import JammerParams
from shared.world_messages import WorldState

TRAIL_POINTS = 600  # per UAV and episode: ten times the shipped episode limit
TIMELINE_KEPT = 200
TIMELINE_IN_FRAME = 30  # the newest entries, in every frame: a page that missed some catches up
JAMMER_FIELDS = ("x", "y", "power_w")
REQUESTS = ('{"x", "y", "power_w"}, the same with "add": true, {"id", "x", "y"}, {"remove": ID} '
            'or {"off": true}')
# What the page draws and writes of each jammer the cloud estimated; the first jammer's
# fields and those of each beside it (``others``).
ESTIMATE_FIELDS = {"present", "id", "x", "y", "power_w", "sd_x_m", "sd_y_m", "sd_power_db",
                   "vx_mps", "vy_mps", "map_version", "measurements"}


class ConsoleState:
    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.revision = 0  # bumped by every change: the server pushes a frame per revision
        self.episode: int | None = None
        self.step: int | None = None
        self.clock: str | None = None
        self._state: WorldState | None = None
        self._trails: list[list[tuple[float, float]]] = []
        self.jammers: JammersInForce = ()
        self.jammer_places: list[JammerPlace] = []
        self.jammer_known = False  # until the world said, "no jammer" is not known either
        self.estimate: JammerEstimate | None = None
        # As the cloud's newest map was published: whether it is provisional, and how many
        # jammers the cloud had counted then, placed or not.
        self.map_provisional = False
        self.jammers_counted: int | None = None
        self.map: SinrMap | None = None
        self._maps: dict[str, dict[str, Any]] = {}  # "served", "true": what the page draws
        self._map_serials = {"served": 0, "true": 0}
        self._outcomes: dict[int, list[str]] = {}  # by episode: a repeated event counts once
        self._timeline: deque[dict[str, Any]] = deque(maxlen=TIMELINE_KEPT)
        self._gone: set[str] = set()
        self.finished = False
        self._frame: tuple[int, bytes] = (-1, b"")

    # -- what comes in ------------------------------------------------------------------------
    def on_world_state(self, state: WorldState) -> None:
        with self._lock:
            if state.episode != self.episode or len(self._trails) != len(state.position):
                self._trails = [[] for _ in state.position]
            for trail, here in zip(self._trails, state.position, strict=True):
                if (not trail or trail[-1] != here) and len(trail) < TRAIL_POINTS:
                    trail.append(here)
            self.episode, self.step, self.clock = state.episode, state.step, state.clock
            self._state = state
            if state.jammer_known:
                self._follow_jammers(tuple(state.jammers_in_force))
                self.jammer_places = list(state.jammer_places)
            self.revision += 1

    def on_event(self, event) -> None:
        """Any event of ``shared.events``: outcomes are counted, the jammer followed, and
        what people care about goes on the timeline (in the supervisor's words)."""
        with self._lock:
            if isinstance(event, UavOutcomes):
                self._outcomes[event.episode] = list(event.outcomes)
            elif event.type == "jammer_changed":
                self._follow_jammers(tuple(event.jammers))
            elif event.type == "run_finished":
                self.finished = True
            elif event.type == "sinr_weights_published":
                self.map_provisional = event.provisional
                self.jammers_counted = event.jammers_counted
            text = describe_event(event.model_dump(mode="json"))
            if text is not None:
                self._note(event.type, event.t, text)
            self.revision += 1

    def on_jammers(self, jammers: JammersInForce) -> None:
        """The jammers in force, as the world answered a command or a ``show``."""
        with self._lock:
            self._follow_jammers(jammers)

    def _follow_jammers(self, jammers: JammersInForce) -> None:
        if not self.jammer_known or jammers != self.jammers:
            self.jammers, self.jammer_known = jammers, True
            # Until the world's next state says, each stands where it was set.
            self.jammer_places = [JammerPlace(id=jammer.id, x=jammer.x, y=jammer.y, on=True)
                                  for jammer in jammers]
            self.revision += 1

    def on_estimate(self, estimate: JammerEstimate) -> None:
        with self._lock:
            self.estimate = estimate
            self.revision += 1

    def on_map(self, update: SinrMap) -> bool:
        """A published SINR map; False for one no newer than the map in service."""
        with self._lock:
            if self.map is not None and update.version <= self.map.version:
                return False
            self.map = update
            self.revision += 1
            return True

    def on_presence(self, name: str, present: bool, t: float) -> None:
        """A process's liveliness token came or went: a process that comes back was
        restarted (by the supervisor, or by hand)."""
        with self._lock:
            if not present:
                self._gone.add(name)
                self._note("presence", t, f"{name} went away")
            elif name in self._gone:
                self._gone.discard(name)
                self._note("presence", t, f"{name} is back (restarted)")
            self.revision += 1

    def set_map(self, which: str, payload: dict[str, Any]) -> None:
        """A map drawn for the page (``served`` or ``true``, see ``CoverageMaps.payload``)."""
        with self._lock:
            self._map_serials[which] += 1
            self._maps[which] = {**payload, "serial": self._map_serials[which]}
            self.revision += 1

    def _note(self, kind: str, t: float, text: str) -> None:
        seq = self._timeline[-1]["seq"] + 1 if self._timeline else 1
        self._timeline.append({"seq": seq, "t": t, "kind": kind, "text": text})

    # -- what goes out ------------------------------------------------------------------------
    def snapshot(self, trails: bool = False) -> dict[str, Any]:
        """``GET /api/state``: the frame, with every UAV's trail this episode if asked."""
        with self._lock:
            view = self._view()
            if trails:
                view["trails"] = [[list(point) for point in trail] for trail in self._trails]
            return view

    def encoded_frame(self) -> tuple[int, bytes]:
        """(revision, JSON) of the frame pushed to every page, encoded once per revision."""
        with self._lock:
            if self._frame[0] != self.revision:
                self._frame = (self.revision, json.dumps(self._view()).encode())
            return self._frame

    def map_payload(self, which: str) -> dict[str, Any] | None:
        with self._lock:
            return self._maps.get(which)

    def current_jammers(self) -> tuple[bool, tuple[JammerParams, ...]]:
        """Whether the jammers are known, and the radio model's of those transmitting now,
        where they are."""
        with self._lock:
            power = {jammer.id: (jammer.power_w, jammer.height_m) for jammer in self.jammers}
            return self.jammer_known, tuple(
                JammerParams(place.x, place.y, *power[place.id]) for place in self.jammer_places
                if place.on and place.id in power)

    def _jammers_view(self) -> list[dict[str, Any]]:
        """Each jammer in force: where it is now and whether it transmits, its power, and the
        path it drives (its start first), if any."""
        places = {place.id: place for place in self.jammer_places}
        view = []
        for jammer in self.jammers:
            place = places.get(jammer.id)
            view.append({
                "id": jammer.id, "power_w": jammer.power_w,
                "x": jammer.x if place is None else place.x,
                "y": jammer.y if place is None else place.y,
                "on": True if place is None else place.on,
                "path": None if jammer.path is None else [
                    [jammer.x, jammer.y], *map(list, jammer.path.waypoints)]})
        return view

    def _view(self) -> dict[str, Any]:
        s = self._state
        uavs = [] if s is None else [
            {"id": i, "x": x, "y": y, "status": status,
             "destination": list(s.destination[i]) if i < len(s.destination) else None}
            for i, ((x, y), status) in enumerate(zip(s.position, s.status, strict=False))]
        served = self.map
        labels = [label for row in self._outcomes.values() for label in row]
        return {
            "revision": self.revision, "episode": self.episode, "step": self.step,
            "clock": self.clock, "uavs": uavs,
            "jammers": self._jammers_view(),
            "jammer_known": self.jammer_known,
            "estimate": None if self.estimate is None else self.estimate.model_dump(
                include={**dict.fromkeys(ESTIMATE_FIELDS, True),
                         "others": {"__all__": ESTIMATE_FIELDS}}),
            "map_version": None if served is None else served.version,
            "map_mode": None if served is None else served.mode,
            "map_accuracy": None if served is None else served.accuracy,
            "map_provisional": self.map_provisional,
            "jammers_counted": self.jammers_counted,
            "maps": {which: m["serial"] for which, m in self._maps.items()},
            "counters": {"episodes": len(self._outcomes),
                         **{o.label: labels.count(o.label) for o in FINAL_OUTCOMES}},
            "timeline": list(self._timeline)[-TIMELINE_IN_FRAME:],
            "finished": self.finished,
        }


def jammer_request(body: Any) -> JammerCommand:
    """The world's command for a ``POST /api/jammer`` body: ``{"x", "y", "power_w"}`` (one
    jammer in place of all), the same with ``"add": true`` (one more), ``{"id", "x", "y"}``
    (move that one there), ``{"remove": ID}`` or ``{"off": true}``; ValueError with a one-line
    reason for anything else."""
    if not isinstance(body, dict):
        raise ValueError(f"expected a JSON object: {REQUESTS}")
    keys = set(body)
    if keys == {"off"} and body["off"] is True:
        return jammer_command("off")
    if keys == {"remove"}:
        return _jammer_command("remove", None, body["remove"], body)
    if keys == {"id", "x", "y"}:
        return _jammer_command("move", (body["x"], body["y"], None, None), body["id"], body)
    if keys in ({*JAMMER_FIELDS}, {*JAMMER_FIELDS, "add"}):
        if body.get("add", True) is not True:
            raise ValueError('"add" is true or left out')
        action = "add" if "add" in body else "set"
        return _jammer_command(action, (*(body[name] for name in JAMMER_FIELDS), None), None,
                               body)
    raise ValueError(f"expected one of {REQUESTS}")


def _jammer_command(action: str, numbers: tuple | None, jammer_id: Any, body: dict
                    ) -> JammerCommand:
    given = [value for value in (numbers or ()) if value is not None]
    if any(isinstance(v, bool) or not isinstance(v, int | float) for v in given):
        raise ValueError("x, y and power_w must be numbers")
    if jammer_id is not None and (isinstance(jammer_id, bool) or not isinstance(jammer_id, int)):
        raise ValueError("a jammer's id is a whole number")
    try:
        return jammer_command(action, numbers, json.dumps(body), jammer_id)
    except UsageError as exc:
        raise ValueError(str(exc)) from None
