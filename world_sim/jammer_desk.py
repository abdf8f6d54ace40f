"""The world's jammers under the operator's hand: what each command on the control key makes
of those in force, and the desk that answers the commands on zenoh's query thread while the
world's main loop applies them between two steps."""

from __future__ import annotations

import threading

import zenoh

from shared import bus
from shared.jammer_messages import (
    JammerCommand,
    JammerInfo,
    JammerReply,
    JammersInForce,
    check_inside,
)
from shared.scenario import MAX_JAMMERS, Scenario
from shared.wire import MessageError, decode, encode


def commanded_jammers(scenario: Scenario, command: JammerCommand, jammers: JammersInForce
                      ) -> JammersInForce:
    """The jammers in force once ``command`` is applied to ``jammers``; ValueError with the
    reason a command is refused."""
    action = command.action
    if action == "show":
        return jammers
    if action == "off" and command.id is None:
        return ()
    if action in ("set", "add", "move"):
        check_inside(scenario, command.x, command.y)
    height = scenario.jammer.height_m if command.height_m is None else command.height_m
    if action == "set":  # one jammer in place of all; of no power, none
        return () if command.power_w == 0 else (JammerInfo(
            x=command.x, y=command.y, power_w=command.power_w, height_m=height),)
    if action == "add":
        free = sorted(set(range(MAX_JAMMERS)) - {jammer.id for jammer in jammers})
        if not free:
            raise ValueError(f"{MAX_JAMMERS} jammers are in force, the most a world flies: "
                             "remove one first")
        return (*jammers, JammerInfo(id=free[0], x=command.x, y=command.y,
                                     power_w=command.power_w, height_m=height))
    index = next((i for i, jammer in enumerate(jammers) if jammer.id == command.id), None)
    if index is None:
        ids = ", ".join(str(jammer.id) for jammer in jammers) or "none"
        raise ValueError(f"no jammer {command.id} (in force: {ids})")
    if action != "move":  # remove, or off ID
        return jammers[:index] + jammers[index + 1:]
    moved = jammers[index].model_copy(update={
        "x": command.x, "y": command.y, "path": None,  # it stands where it was put
        **({} if command.power_w is None else {"power_w": command.power_w}),
        **({} if command.height_m is None else {"height_m": command.height_m})})
    return jammers[:index] + (moved,) + jammers[index + 1:]


class JammerDesk:
    """Jammer commands come in on zenoh's query thread; they are checked and answered there,
    and the main loop applies the accepted ones between two steps."""

    def __init__(self, scenario: Scenario, jammers: JammersInForce, dropped: bus.Dropped, key: str):
        self.scenario = scenario
        self.dropped = dropped
        self.key = key
        self._lock = threading.Lock()
        self._current = jammers
        self._pending: list[JammersInForce] = []  # accepted, in order
        self.episode = 0
        self.step = 0

    def current(self) -> JammersInForce:
        """The jammers once every accepted command is applied."""
        with self._lock:
            return self._accepted_last()

    def _accepted_last(self) -> JammersInForce:
        return self._pending[-1] if self._pending else self._current

    def handle(self, query: zenoh.Query) -> None:
        payload = query.payload
        try:
            command = (JammerCommand(action="show") if payload is None
                       else decode(JammerCommand, payload.to_bytes()))
        except MessageError as exc:
            self.dropped.add(self.key, str(exc))
            query.reply(self.key, encode(self._reply(False, str(exc))))
            return
        reason = None
        with self._lock:
            try:
                jammers = commanded_jammers(self.scenario, command, self._accepted_last())
            except ValueError as exc:
                reason = str(exc)
            else:
                if jammers != self._accepted_last():  # a command that changes nothing says nothing
                    self._pending.append(jammers)
        query.reply(self.key, encode(self._reply(reason is None, reason)))

    def _reply(self, accepted: bool, reason: str | None) -> JammerReply:
        return JammerReply(accepted=accepted, reason=reason, jammers=list(self.current()),
                           episode=self.episode, step=self.step)

    def in_force(self) -> JammersInForce:
        """The jammers the world flies with now (accepted commands wait for the next step)."""
        with self._lock:
            return self._current

    def schedule(self, jammers: JammersInForce) -> None:
        """The run's jammer schedule sets the jammers, as a command would."""
        with self._lock:
            if jammers != self._accepted_last():
                self._pending.append(jammers)

    def take(self) -> list[JammersInForce]:
        """The jammer sets accepted since the last call, in order."""
        with self._lock:
            taken, self._pending = self._pending, []
            if taken:
                self._current = taken[-1]
            return taken
