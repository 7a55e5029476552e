"""`companion sim --start-error`: parsing, the seeded start pose and the daemon's hint."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.errors import InputError
from companion.geometry import frames
from companion.sim.start_error import StartError, StartPose, parse_start_error, start_hint, start_pose


def test_parse_start_error() -> None:
    assert parse_start_error("1.0,30") == StartError(1.0, 30.0)
    assert parse_start_error(" 0.5 , 0 ").text() == "0.5,0"
    for bad, what in (("1.0", "METRES,DEGREES"), ("a,30", "numbers"), ("-1,30", "horizontal_m"),
                      ("1,200", "yaw_deg"), ("nan,3", "horizontal_m")):
        with pytest.raises(InputError, match=what):
            parse_start_error(bad)


def test_start_pose_is_seeded_and_within_the_error() -> None:
    err = StartError(1.0, 30.0)
    poses = [start_pose(err, seed) for seed in range(400)]
    assert start_pose(err, 7) == poses[7]  # the same seed, the same start
    r = np.array([math.hypot(p.north_m, p.east_m) for p in poses])
    yaw = np.degrees([p.yaw_rad for p in poses])
    assert r.max() <= 1.0 and np.abs(yaw).max() <= 30.0
    # uniform over the disc and the yaw interval: the quartiles of r^2 and yaw where they belong
    assert np.median(r**2) == pytest.approx(0.5, abs=0.08)
    assert np.percentile(yaw, 75) == pytest.approx(15.0, abs=3.0)
    assert start_pose(StartError(), 3) == StartPose(0.0, 0.0, 0.0)


def test_the_daemon_gets_the_configured_start_unless_asked_for_the_true_one() -> None:
    true = start_pose(StartError(1.0, 30.0), 2)
    np.testing.assert_allclose(start_hint(true), np.eye(4))
    T = start_hint(true, seed_true_pose=True)
    np.testing.assert_allclose(T[:3, 3], [true.north_m, true.east_m, 0.0])
    assert frames.yaw_from_rotation(T[:3, :3]) == pytest.approx(true.yaw_rad)


def test_offset_lla_moves_the_sitl_home_by_metres() -> None:
    from companion.sim.start_error import EARTH_RADIUS_M, offset_lla

    lat, lon, alt = offset_lla((47.4, 8.5, 488.0), 1.0, -2.0)
    assert alt == 488.0
    assert math.radians(lat - 47.4) * EARTH_RADIUS_M == pytest.approx(1.0, rel=1e-9)
    assert math.radians(lon - 8.5) * EARTH_RADIUS_M * math.cos(math.radians(47.4)) == pytest.approx(-2.0, rel=1e-9)


def test_the_report_says_why_poses_were_withheld_on_the_deck() -> None:
    """When the start-hint lock cannot be verified (the field appearance on the deck: a shaded limb as dark as
    the ground), the daemon withholds its poses and the sim's report says so, with the last check's verdict."""
    from types import SimpleNamespace

    from companion.daemon.hint_check import HintCheck, HintChecker
    from companion.sim.run import _withheld_reason

    checker = HintChecker()
    checker.last = HintCheck("no-confident-pose", status="no hypothesis agrees with the image edges")
    daemon = SimpleNamespace(counters=SimpleNamespace(poses_withheld=0),
                             pipeline=SimpleNamespace(hint_checker=checker))
    assert _withheld_reason(daemon) == ""
    daemon.counters.poses_withheld = 452
    text = _withheld_reason(daemon)
    assert "452 withheld" in text and "rack_verify_start" in text
    assert "no-confident-pose, no hypothesis agrees with the image edges" in text
    daemon.pipeline = None  # no rack pipeline: the count alone
    assert "452 withheld" in _withheld_reason(daemon) and "last check" not in _withheld_reason(daemon)
