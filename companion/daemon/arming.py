"""Arming through the autopilot's own readiness, and who owns the flight mode.

Arming: a real ArduCopter with external navigation is not ready to arm until its EKF has
aligned on the vision poses (about 14 s after they start) and its home is set; until then ARM
is refused with MAV_RESULT_FAILED and an "Arm: ..." STATUSTEXT. So the daemon waits for the
autopilot's pre-arm check (SYS_STATUS MAV_SYS_STATUS_PREARM_CHECK health, when it reports it),
then arms, retrying a refusal once a second until `timeout_s`, and fails with the autopilot's
last reason. Progress goes to the GCS every few seconds.

Mode ownership (one rule): whoever starts or resumes motion makes sure the autopilot is in the
velocity-setpoint mode (ArduPilot GUIDED, PX4 OFFBOARD) first, and says so when it cannot.
`ModeOwner` decides it, synchronously: the daemon arms it on mission start and resume; the
first motion goal after that switches the mode. A mode change made by anyone else while a
mission moves the vehicle (a pilot on the sticks, an autopilot failsafe) pauses the mission
instead of being fought.
"""

from __future__ import annotations

import enum
from collections.abc import Awaitable, Callable
from dataclasses import dataclass
from typing import Any

from companion.errors import CommandDenied, CompanionError, LinkError

__all__ = ["ModeDecision", "ModeOwner", "arm_when_ready", "enter_guided"]


async def arm_when_ready(link: Any, sleep: Callable[[float], Awaitable[None]], now: Callable[[], float], *,
                         timeout_s: float, say: Callable[[str], None], progress_every_s: float = 5.0) -> float:
    """Wait for the autopilot's pre-arm readiness, then arm; returns the seconds waited.

    Raises `LinkError` naming the autopilot's last arming text when it is not armed within `timeout_s`.
    """
    t0 = now()
    deadline = t0 + float(timeout_s)
    next_say = t0 + progress_every_s
    last_error: str | None = None
    while True:
        state = link.state
        if state.armed:
            return now() - t0
        ready = state.prearm_ok is not False  # None: the autopilot does not report it; try
        if ready:
            try:
                await link.arm()
                return now() - t0
            except CommandDenied as exc:
                last_error = str(exc)
        if now() >= deadline:
            why = link.state.arming_text or last_error or "pre-arm checks not passing"
            raise LinkError(f"autopilot not ready to arm after {timeout_s:g} s: {why}")
        if now() >= next_say:
            next_say = now() + progress_every_s
            why = link.state.arming_text or "pre-arm checks"
            say(f"waiting for the autopilot to be ready to arm ({now() - t0:.0f} s): {why}")
        await sleep(1.0 if ready else 0.2)


class ModeDecision(enum.Enum):
    NOTHING = "nothing"
    ENTER_GUIDED = "enter-guided"  # switch the autopilot to the velocity-setpoint mode now
    PAUSE = "pause"  # someone else changed the mode under a moving mission: pause it


@dataclass
class ModeOwner:
    """Decides when the daemon switches to the guided mode and when a foreign mode change pauses.

    `claim()` on mission start and resume (and after a take-off the daemon commanded); `decide()`
    every control step with what the step is about to do.
    """

    claimed: bool = False
    owned: bool = False  # the autopilot is in the guided mode because we put it there
    switching: bool = False
    switched_at_s: float = float("-inf")  # when our last mode change was accepted (clock s)

    def claim(self) -> None:
        self.claimed = True

    def accepted(self, now_s: float) -> None:
        """Our switch to the guided mode was accepted by the autopilot at `now_s`."""
        self.claimed = False
        self.owned = True
        self.switched_at_s = now_s

    def release(self) -> None:
        self.claimed = False
        self.owned = False

    def decide(self, *, moving: bool, armed: bool, airborne: bool, mode: str | None, guided_mode: str,
               request_pending: bool, mode_stamp_s: float | None = None) -> ModeDecision:
        """`moving`: the step has a motion goal and safety allows it; `request_pending`: a discrete
        request (arm, take-off, land, photo) is in progress and owns the mode meanwhile;
        `mode_stamp_s`: when `mode` was reported (a heartbeat from before our own accepted switch
        still shows the old mode and is not a foreign change)."""
        if request_pending or self.switching or not moving or not armed or not airborne:
            return ModeDecision.NOTHING
        if mode_stamp_s is not None and mode_stamp_s <= self.switched_at_s:
            return ModeDecision.NOTHING
        if mode == guided_mode:
            if self.claimed:
                self.claimed = False
                self.owned = True
            return ModeDecision.NOTHING
        if self.claimed:
            return ModeDecision.ENTER_GUIDED
        if self.owned:
            self.owned = False
            return ModeDecision.PAUSE
        return ModeDecision.NOTHING


async def enter_guided(owner: ModeOwner, enter: Callable[[], Awaitable[None]], now: Callable[[], float]) -> str | None:
    """Run the switch (`enter`); returns None on success, else the reason it failed."""
    owner.switching = True
    try:
        await enter()
    except CompanionError as exc:
        return str(exc)
    finally:
        owner.switching = False
    owner.accepted(now())
    return None
