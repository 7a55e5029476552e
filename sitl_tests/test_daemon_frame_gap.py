"""A gap in the camera's frames: the daemon re-seeds its rack tracker from the filter and keeps what the tracker
learnt of the scene (`RackTracker.reset(keep_appearance=True)`), so the first frame after the gap costs one solve,
not four; a re-seed for another reason still forgets it. Fake autopilot, manual clock, inline vision."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sitl_tests.daemon_harness import rig


async def test_a_frame_gap_reseeds_the_tracker_keeping_its_appearance(tmp_path: Path) -> None:
    async with rig(tmp_path) as r:
        d = r.daemon
        assert d.pipeline is not None and d.pipeline.rack_tracker is not None
        tracker = d.pipeline.rack_tracker
        resets: list[bool] = []
        real = tracker.reset

        def spy(T: Any, *args: Any, keep_appearance: bool = False, **kwargs: Any) -> None:
            resets.append(keep_appearance)
            real(T, *args, keep_appearance=keep_appearance, **kwargs)

        tracker.reset = spy  # type: ignore[method-assign]
        await r.advance(1.0)
        assert resets == []  # tracking: no re-seed
        sent = d.counters.poses_sent
        r.camera.unplugged = True
        await r.advance(0.45)
        r.camera.unplugged = False
        await r.advance(1.0)
        logged = [rec["reason"] for rec in r.logged("rack-tracker-reset")]
        assert any(reason.startswith("frame gap") for reason in logged), logged
        assert resets and resets[0] is True, (resets, logged)
        assert d.counters.poses_sent >= sent + 8  # the stream came back at once (10 frames/s)
        # another reason (the tracker failing twice) forgets the appearance
        d._rack_reset_pending, d._rack_reset_reason = True, "tracker: no visible limb"
        await r.advance(0.3)
        assert resets[-1] is False, resets
