"""The rack-end search leg: find the position along the pipes before a waypoint is placed with it.

Over the middle of a rack nothing in view tells where along the pipes (rack y) the vehicle is: an
acquisition on the deck keeps the configured start's y (docs/acquire.md, "y on the deck"), up to the
start error off. The rack's ends do tell it (`companion.vision.rack.acquire_end.rack_end_fix`, run by
the daemon on every frame while y is unobserved), but only once an end is in the camera's footprint.
When the mission is about to fly to a waypoint that needs y, `AlongPipeSearch` flies a bounded leg
toward the nearest end of the rack (in the estimate) at the current height, x and heading, slowly,
until the end is seen; if it is not seen within the leg, it fails and the daemon holds.

How far (`plan_leg`): with the estimated camera at distance a from the end, along-pipe std sigma, and
the end seen from r away at this height (`end_reach_m`), the true position is within a + k sigma of
the end (k = `sigmas`), so the end is in view after at most a + k sigma - r; and the estimated camera
never goes more than `margin_m` past the end: the leg is min(a + k sigma - r, a + margin_m). The end
not being in view at the start means the camera is truly more than r from it, so even when the end
detector fails the leg ends at most a + margin_m - r past the true end (0.4 m with the defaults at the
example mission's 2.5 m, where the pipes still fill part of the image); the daemon also stops the
leg as soon as the rack tracker is no longer locked.

Pure: arrays in, frozen dataclasses out, time as an argument (the state machine keeps its own state).
Frames: `rack` (pipes along +y, z up), `ned`, `body`, `cam` as in DESIGN.md; SI units.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass

import numpy as np

from companion.camera import PinholeCamera
from companion.checks import FloatArray, check_transform
from companion.errors import InputError

__all__ = ["AlongPipeSearch", "SearchLeg", "SearchLimits", "SearchState", "SearchStep", "end_reach_m", "plan_leg"]


class SearchState(enum.StrEnum):
    """States of the search: IDLE -> SEARCHING -> FOUND | FAILED; FAILED -> OVERRIDDEN (operator)."""

    IDLE = "idle"
    SEARCHING = "searching"
    FOUND = "found"  # the along-pipe position was observed (rack end or crossing pipe)
    FAILED = "failed"  # not found within the leg, tracker lost, or timed out: hold
    OVERRIDDEN = "overridden"  # the operator resumed after a failure: fly on with the prior's y


@dataclass(frozen=True)
class SearchLimits:
    """How the leg is flown.

    speed_m_s: leg speed (m/s); margin_m: how far past the rack's end (in the estimate) the camera may go
    (m); sigmas: the leg covers the along-pipe prior to this many standard deviations; arrive_m /
    settle_s: the leg's end counts as reached within this distance (m) held this long (s); spare_s: time
    allowed beyond length / speed (s); min_side_m, margin_px: what `rack_end_fix` needs to see of the
    limbs beyond the end (m) and of the image border (px).
    """

    speed_m_s: float = 0.2
    margin_m: float = 0.5
    sigmas: float = 2.0
    arrive_m: float = 0.05
    settle_s: float = 1.0
    spare_s: float = 15.0
    min_side_m: float = 0.15
    margin_px: float = 6.0

    def __post_init__(self) -> None:
        for name in ("speed_m_s", "sigmas", "arrive_m", "spare_s"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0.0):
                raise InputError(f"SearchLimits.{name}: must be finite and > 0, got {getattr(self, name)!r}")
        for name in ("margin_m", "settle_s", "min_side_m", "margin_px"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0.0):
                raise InputError(f"SearchLimits.{name}: must be finite and >= 0, got {getattr(self, name)!r}")


@dataclass(frozen=True)
class SearchLeg:
    """A planned leg. Poses are body poses in NED (4x4); y values are the camera's rack y (m).

    end_y_m: the rack end looked for (0 or the rack's length); direction: +1 toward rack +y, -1 toward
    -y; length_m: how far the leg goes (m); reach_m: distance from the end at which it comes into view
    at this height (m); y_std_m: the along-pipe std the leg covers (m); y_start_m: the camera's rack y at
    the start (estimate).
    """

    T_ned_body_start: FloatArray
    T_ned_body_goal: FloatArray
    end_y_m: float
    direction: float
    length_m: float
    reach_m: float
    y_std_m: float
    y_start_m: float


@dataclass(frozen=True)
class SearchStep:
    """One step's outcome: `goal` (4x4 body pose in NED) to servo to while SEARCHING, else None;
    `state`; `message` when the state changed on this step ("" otherwise); `flown_m`: distance flown
    along the leg so far (m)."""

    goal: FloatArray | None
    state: SearchState
    message: str
    flown_m: float


def end_reach_m(camera: PinholeCamera, T_rack_cam: FloatArray, limb_z_m: float, *, min_side_m: float = 0.15,
                margin_px: float = 6.0, max_m: float = 20.0) -> float:
    """Along-pipe distance (m) from the camera within which a rack end is seen well enough to be located.

    The pipes' limbs lie near rack z = `limb_z_m` (their axes' height); the end is located when its
    limbs are in view `min_side_m` beyond it, `margin_px` inside the image. Both directions along the
    pipes are checked (the camera's footprint is not always centred); the smaller reach is returned
    (0 when nothing along the pipes at that height is in view, e.g. looking at the horizon).
    """
    T = check_transform(T_rack_cam, "T_rack_cam")
    o = T[:3, 3]
    t = np.arange(0.0, max_m, 0.01)
    reach = []
    for sign in (1.0, -1.0):
        p_rack = np.stack([np.full_like(t, o[0]), o[1] + sign * t, np.full_like(t, float(limb_z_m))], axis=1)
        uv = camera.project((p_rack - o) @ T[:3, :3])
        inside = np.all(np.isfinite(uv), axis=1) & (uv[:, 0] >= margin_px) & (uv[:, 1] >= margin_px) \
            & (uv[:, 0] <= camera.width - 1 - margin_px) & (uv[:, 1] <= camera.height - 1 - margin_px)
        # the first sample outside the image ends the footprint in this direction
        n_in = int(np.argmin(inside)) if not bool(np.all(inside)) else t.size
        reach.append(max(0.0, float(t[max(n_in - 1, 0)]) - min_side_m) if n_in > 0 else 0.0)
    return min(reach)


def plan_leg(T_ned_body: FloatArray, T_ned_rack: FloatArray, T_body_cam: FloatArray, camera: PinholeCamera,
             rack_length_m: float, limb_z_m: float, y_std_m: float, limits: SearchLimits) -> SearchLeg:
    """The leg toward the nearest rack end from the body pose `T_ned_body` (estimate), see the module docstring.

    The goal keeps the current height, rack x and heading; only rack y changes.
    """
    T_nb = check_transform(T_ned_body, "T_ned_body")
    T_nr = check_transform(T_ned_rack, "T_ned_rack")
    T_rack_cam = np.linalg.inv(T_nr) @ T_nb @ check_transform(T_body_cam, "T_body_cam")
    if not (math.isfinite(y_std_m) and y_std_m >= 0.0):
        raise InputError(f"y_std_m: must be finite and >= 0, got {y_std_m!r}")
    y_cam = float(T_rack_cam[1, 3])
    end_y = 0.0 if y_cam <= 0.5 * rack_length_m else float(rack_length_m)
    direction = -1.0 if end_y == 0.0 else 1.0
    reach = end_reach_m(camera, T_rack_cam, limb_z_m, min_side_m=limits.min_side_m, margin_px=limits.margin_px)
    a = direction * (end_y - y_cam)  # distance to the end ahead (negative: already past it)
    length = max(0.0, min(a + limits.sigmas * y_std_m - reach, a + limits.margin_m))
    T_goal = T_nb.copy()
    T_goal[:3, 3] += length * direction * (T_nr[:3, :3] @ np.array([0.0, 1.0, 0.0]))
    return SearchLeg(T_ned_body_start=T_nb.copy(), T_ned_body_goal=T_goal, end_y_m=end_y, direction=direction,
                     length_m=length, reach_m=reach, y_std_m=float(y_std_m), y_start_m=y_cam)


class AlongPipeSearch:
    """The search's state machine (see the module docstring); the daemon feeds it one step per control step.

    `start(now_s, leg)` begins a leg; `step(now_s, T_ned_body, y_known=..., tracker_locked=..., active=...)`
    advances it: FOUND as soon as `y_known`, FAILED when the tracker is not locked, when the leg's end
    was reached and held `settle_s` without the end seen, or after length / speed + `spare_s` of active
    time (time with `active` false, e.g. a safety hold, does not count). `override()` after a failure
    (the operator resumes): OVERRIDDEN. One instance per mission.
    """

    def __init__(self, limits: SearchLimits | None = None) -> None:
        self.limits = limits or SearchLimits()
        self.state = SearchState.IDLE
        self.leg: SearchLeg | None = None
        self._active_s = 0.0
        self._last_s: float | None = None
        self._arrived_s: float | None = None
        self.flown_m = 0.0

    def start(self, now_s: float, leg: SearchLeg, *, tracker_locked: bool) -> SearchStep:
        """Begin `leg` (state SEARCHING). It fails at once without a locked rack tracker (nothing would see
        the end), and when it has (almost) no length (the prior puts the end in view, yet it is not found)."""
        self.leg = leg
        self.state = SearchState.SEARCHING
        self._active_s, self._last_s, self._arrived_s, self.flown_m = 0.0, float(now_s), None, 0.0
        if not tracker_locked:
            return self._fail("rack tracker not locked: cannot look for the rack's end")
        if leg.length_m < self.limits.arrive_m:
            return self._fail(f"rack end (y = {leg.end_y_m:g} m) not found although the along-pipe prior "
                              f"(±{leg.y_std_m:.2f} m) puts it in view")
        toward = "+y" if leg.direction > 0 else "-y"
        return SearchStep(goal=leg.T_ned_body_goal.copy(), state=self.state, flown_m=0.0, message=(
            f"along-pipe position not observed (±{leg.y_std_m:.2f} m): looking for the rack's end, "
            f"up to {leg.length_m:.2f} m toward rack {toward} at {self.limits.speed_m_s:g} m/s"))

    def override(self) -> None:
        """The operator resumed after a failure: fly on with the prior's along-pipe position."""
        if self.state is SearchState.FAILED:
            self.state = SearchState.OVERRIDDEN

    def step(self, now_s: float, T_ned_body: FloatArray, *, y_known: bool, tracker_locked: bool,
             active: bool) -> SearchStep:
        """Advance the leg to `now_s` (s) with the body pose estimate `T_ned_body` (NED)."""
        leg = self.leg
        if self.state is not SearchState.SEARCHING or leg is None:
            return SearchStep(None, self.state, "", self.flown_m)
        now_s = float(now_s)
        dt = 0.0 if self._last_s is None else max(0.0, now_s - self._last_s)
        self._last_s = now_s
        if active:
            self._active_s += dt
        p = check_transform(T_ned_body, "T_ned_body")[:3, 3]
        d_ned = leg.T_ned_body_goal[:3, 3] - leg.T_ned_body_start[:3, 3]
        unit = d_ned / max(float(np.linalg.norm(d_ned)), 1e-9)
        if y_known:
            self.state = SearchState.FOUND
            return SearchStep(None, self.state, f"rack end in view after {self.flown_m:.2f} m of the search leg: "
                              "along-pipe position observed, mission goes on", self.flown_m)
        # progress along the leg in the estimate (the estimate's along-pipe offset is constant until the fix)
        self.flown_m = max(self.flown_m, float(np.dot(p - leg.T_ned_body_start[:3, 3], unit)))
        if not tracker_locked:
            return self._fail(f"rack tracker not locked after {self.flown_m:.2f} m of the search leg")
        if float(np.linalg.norm(leg.T_ned_body_goal[:3, 3] - p)) <= self.limits.arrive_m:
            self._arrived_s = now_s if self._arrived_s is None else self._arrived_s
            if now_s - self._arrived_s >= self.limits.settle_s:
                return self._fail(f"rack end (y = {leg.end_y_m:g} m) not in view at the end of the "
                                  f"{leg.length_m:.2f} m search leg")
        else:
            self._arrived_s = None
        if self._active_s > leg.length_m / self.limits.speed_m_s + self.limits.spare_s:
            return self._fail(f"search leg timed out after {self._active_s:.0f} s ({self.flown_m:.2f} m flown)")
        return SearchStep(leg.T_ned_body_goal.copy(), self.state, "", self.flown_m)

    def _fail(self, reason: str) -> SearchStep:
        self.state = SearchState.FAILED
        return SearchStep(None, self.state, reason, self.flown_m)
