"""The console's side of the bus: it subscribes to what an operator may see (the world's
state, events, the cloud's maps and jammer estimates, who is alive), folds each message into
the ``ConsoleState``, draws the maps off zenoh's threads, and sends the operator's jammer
commands to the world as ``jamnav jammer`` does."""

from __future__ import annotations

import logging
import threading
import time

import zenoh

from jamnav.console.maps import CoverageMaps
from jamnav.console.state import ConsoleState
from planning.networks import WeightsError
from shared import bus
from shared.cloud_messages import SinrMap
from shared.events import decode_event
from shared.jammer_messages import JammerCommand, JammerEstimate, JammerReply
from shared.topics import Topics
from shared.wire import MessageError
from shared.world_messages import WorldState

ASK_EVERY_S = 1.0  # until the world and the cloud have answered once: they may start later
DRAW_EVERY_S = 0.1


class Feed:
    def __init__(self, session: zenoh.Session, topics: Topics, state: ConsoleState,
                 maps: CoverageMaps, log: logging.Logger):
        self.session, self.topics, self.state, self.maps, self.log = (
            session, topics, state, maps, log)
        self.dropped = bus.Dropped(log)
        self._lock = threading.Lock()
        self._undrawn: SinrMap | None = None
        self._drawn_jammers: tuple | None = None
        self._declared: list = []

    def start(self) -> None:
        t, s = self.topics, self.session
        self._declared = [
            bus.subscribe(s, t.state, WorldState, self.state.on_world_state, self.dropped),
            bus.subscribe(s, t.jammer_estimate, JammerEstimate, self.state.on_estimate,
                          self.dropped),
            bus.subscribe(s, t.sinr_map, SinrMap, self._on_map, self.dropped),
            s.declare_subscriber(t.event("*"), self._on_event),
            s.liveliness().declare_subscriber(t.alive(), self._on_presence, history=True),
        ]

    def run(self, stop: threading.Event) -> None:
        """Ask for what is not known yet, and draw new maps, until ``stop``."""
        next_ask = 0.0
        while not stop.wait(DRAW_EVERY_S):
            if time.monotonic() >= next_ask:
                self._ask_for_missing()
                next_ask = time.monotonic() + ASK_EVERY_S
            self._draw()

    def command(self, command: JammerCommand) -> JammerReply:
        """Send ``command`` to the world (BusError, or QueryRefused, if it cannot be); the
        jammer it puts in force shows at once."""
        reply = bus.query(self.session, self.topics.jammer_control, JammerReply, command)
        if reply.accepted:
            self.state.on_jammers(tuple(reply.jammers))
        return reply

    # -- zenoh's threads: store and return ---------------------------------------------------
    def _on_map(self, update: SinrMap) -> None:
        if self.state.on_map(update):
            with self._lock:
                self._undrawn = update

    def _on_event(self, sample: zenoh.Sample) -> None:
        try:
            self.state.on_event(decode_event(sample.payload.to_bytes()))
        except MessageError as exc:
            self.dropped.add(self.topics.event("*"), str(exc))

    def _on_presence(self, sample: zenoh.Sample) -> None:
        role, ident = self.topics.role_and_id(str(sample.key_expr))
        self.state.on_presence(f"{role}-{ident}", sample.kind == zenoh.SampleKind.PUT,
                               time.time())

    # -- the feed's own thread ---------------------------------------------------------------
    def _ask_for_missing(self) -> None:
        """The jammer in force and the map in service, until the world and the cloud have
        answered: after that, events and puts keep them current."""
        if not self.state.jammer_known and (reply := self._ask(
                self.topics.jammer_control, JammerReply, JammerCommand(action="show"))):
            self.state.on_jammers(tuple(reply.jammers))
        if self.state.map is None and (update := self._ask(self.topics.sinr_map, SinrMap)):
            self._on_map(update)

    def _ask(self, key: str, kind, payload=None):
        try:
            return bus.query(self.session, key, kind, payload, timeout=0.5)
        except bus.BusError:
            return None

    def _draw(self) -> None:
        with self._lock:
            update, self._undrawn = self._undrawn, None
        if update is not None:
            try:
                levels = self.maps.served(update)
            except WeightsError as exc:
                self.log.warning("SINR map v%d cannot be drawn: %s", update.version, exc)
            else:
                self.state.set_map("served", self.maps.payload(
                    levels, version=update.version, mode=update.mode))
        known, jammers = self.state.current_jammers()
        if known and (known, jammers) != self._drawn_jammers:
            self._drawn_jammers = (known, jammers)
            self.state.set_map("true", self.maps.payload(
                self.maps.true(jammers), jammers=[jammer._asdict() for jammer in jammers]))
