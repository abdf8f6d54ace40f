"""The cloud's desk of rounds on the lockstep clock."""

from __future__ import annotations

from cloud_service.rounds import RoundDesk
from shared.cloud_messages import MeasurementUpload
from shared.world_messages import RoundOpened
from tests.support import upload_of


def _upload(uav: int, round_number: int) -> MeasurementUpload:
    return upload_of(uav, [], round_number)


def test_rounds_close_in_order_once_their_uploads_are_in():
    desk = RoundDesk(delay=2, serving=0)
    desk.open(RoundOpened(round=101, flown_s=2.0, uavs=[0, 1]))
    desk.open(RoundOpened(round=100, flown_s=1.0, uavs=[0]))
    desk.add(_upload(1, 101), "b")
    desk.add(_upload(0, 101), "a")
    assert desk.next_closing(0.0) is None  # round 100 is older and waits for UAV 0
    desk.add(_upload(0, 100), "c")
    opened, uploads = desk.next_closing(0.0)
    assert opened.round == 100 and [reply for _, reply in uploads] == ["c"]
    opened, uploads = desk.next_closing(0.0)
    assert opened.round == 101 and [reply for _, reply in uploads] == ["a", "b"]
    assert desk.closed_through == 101 and desk.stale(101) and not desk.stale(102)


def test_a_round_already_closed_opens_nothing_and_holds_up_no_later_round():
    """A replayed or forged RoundOpened of a closed round would be the oldest open round, and
    every later round would wait ROUND_WAIT_S behind it."""
    desk = RoundDesk(delay=0, serving=0)
    desk.open(RoundOpened(round=100, flown_s=1.0, uavs=[0]))
    desk.add(_upload(0, 100), "first")
    assert desk.next_closing(0.0)[0].round == 100
    desk.open(RoundOpened(round=7, flown_s=1.0, uavs=[0, 1]))  # stale: never answered
    desk.open(RoundOpened(round=101, flown_s=2.0, uavs=[0]))
    desk.add(_upload(0, 101), "second")
    opened, uploads = desk.next_closing(0.0)
    assert opened.round == 101 and [reply for _, reply in uploads] == ["second"]
    assert desk.next_closing(0.0) is None


def test_a_round_no_upload_came_for_is_forgotten_and_marks_no_later_round_stale():
    """A forged round far ahead of the world's would, closed when overdue, put the rounds the
    world opens next behind the desk's closed mark: they would all be ignored."""
    desk = RoundDesk(delay=0, serving=0)
    desk.open(RoundOpened(round=10**12, flown_s=1.0, uavs=[0]))
    assert desk.next_closing(0.0) is None
    later = 1e9  # past ROUND_WAIT_S
    assert desk.next_closing(later) is None and desk.closed_through == -1
    desk.open(RoundOpened(round=100, flown_s=1.0, uavs=[0]))
    desk.add(_upload(0, 100), "real")
    opened, uploads = desk.next_closing(later)
    assert opened.round == 100 and [reply for _, reply in uploads] == ["real"]
