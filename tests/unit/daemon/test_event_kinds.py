"""Subscribers that watch some event kinds are not woken by the others."""

from __future__ import annotations

import pytest

from robocal.daemon.events import EventBus


async def test_a_subscriber_of_state_events_gets_no_pose_events() -> None:
    bus = EventBus()
    async with bus.subscribe(("state",)) as states, bus.subscribe() as every:
        bus.emit("pose", "c1", pose=0, purpose="calibration", poses_measured=1, poses_total=2,
                 attempts=1, distance_mm=None)
        bus.emit("state", "c1", state="measured", reason="all poses measured",
                 poses_measured=2, poses_total=2)
        assert states.qsize() == 1 and every.qsize() == 2
        got = states.get_nowait()
        assert got is not None and got["kind"] == "state" and got["seq"] == 2
        bus.close()
        assert states.get_nowait() is None  # the bus closing reaches every subscriber


async def test_unknown_kinds_are_refused() -> None:
    bus = EventBus()
    with pytest.raises(ValueError, match="posed"):
        async with bus.subscribe(("posed",)):
            pass
