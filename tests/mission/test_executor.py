"""Mission executor: success end to end on a kinematic vehicle, timeout -> abort -> hold, pause/resume."""

from __future__ import annotations

import math

import numpy as np
import pytest

from companion.control import ServoLaw, VelocityCommand
from companion.geometry import se3
from companion.geometry.frames import default_T_ned_rack, rotation_from_euler_zyx, yaw_from_rotation
from companion.mission import (
    EventKind,
    ExecutorOutput,
    MissionError,
    MissionExecutor,
    NavSnapshot,
    RackLayout,
    RequestKind,
    State,
    load_mission,
    parse_mission,
)
from tests.mission.test_parser import EXAMPLES, doc


def pose(x: float, y: float, z: float, yaw: float = 0.0) -> np.ndarray:
    return se3.make(rotation_from_euler_zyx(0.0, 0.0, yaw), np.array([x, y, z]))


class Vehicle:
    """Kinematic multirotor + a daemon that honours requests at once (photo, arm, takeoff, land)."""

    def __init__(self, ex: MissionExecutor, T: np.ndarray | None = None, *, armed: bool = False,
                 landed: bool = True, photo_ok: bool = True) -> None:
        self.ex = ex
        self.T = pose(0.0, 0.0, 0.0) if T is None else T
        self.armed, self.landed = armed, landed
        self.photo_ok = photo_ok
        self.ok = True
        self.landing = False
        self.law = ServoLaw()
        self.cmd = VelocityCommand.zero()
        self.photos: list[str] = []
        self.holds = 0
        self.outputs: list[ExecutorOutput] = []
        self.commands: list[VelocityCommand] = []

    def nav(self, t: float) -> NavSnapshot:
        return NavSnapshot(stamp_s=t, T_ned_body=self.T, ok=self.ok, armed=self.armed, landed=self.landed)

    def run(self, t0: float, t1: float, dt: float = 0.1) -> float:
        t = t0
        while t < t1 - 1e-9 and self.ex.state not in (State.COMPLETED, State.FAILED, State.ABORTED):
            out = self.ex.step(t, self.nav(t))
            self.outputs.append(out)
            self.handle(out, t)
            self.move(out, dt)
            t = round(t + dt, 9)
        return t

    def handle(self, out: ExecutorOutput, t: float) -> None:
        req = out.request
        if req is None:
            return
        if req.kind is RequestKind.ARM:
            self.armed = True
            self.ex.notify(req.id, True, t)
        elif req.kind is RequestKind.TAKEOFF:
            self.landed = False
            self.ex.notify(req.id, True, t)
        elif req.kind is RequestKind.PHOTO:
            self.photos.append(str(req.camera))
            self.ex.notify(req.id, self.photo_ok, t, "" if self.photo_ok else "camera unplugged")
        elif req.kind is RequestKind.LAND:
            self.landing = True
            self.ex.notify(req.id, True, t)
        elif req.kind is RequestKind.HOLD:
            self.holds += 1

    def move(self, out: ExecutorOutput, dt: float) -> None:
        if self.landing:
            p = self.T[:3, 3].copy()
            p[2] = min(0.0, p[2] + 0.5 * dt)
            self.T = se3.make(self.T[:3, :3], p)
            if p[2] >= 0.0:
                self.landed, self.landing, self.armed = True, False, False
            return
        if out.goal is None or self.landed:
            return
        self.cmd = self.law.command(self.T, out.goal.T_ned_body_goal, max_speed_m_s=out.goal.max_speed_m_s,
                                    dt_s=dt, previous=self.cmd)
        self.commands.append(self.cmd)
        yaw = float(yaw_from_rotation(self.T[:3, :3])) + self.cmd.yaw_rate_rad_s * dt
        p = self.T[:3, 3] + dt * np.array([self.cmd.vx_m_s, self.cmd.vy_m_s, self.cmd.vz_m_s])
        self.T = pose(p[0], p[1], p[2], yaw)


def events(v: Vehicle) -> list[EventKind]:
    return [e.kind for out in v.outputs for e in out.events]


def test_fig6_mission_completes_on_a_kinematic_vehicle() -> None:
    mission = load_mission(EXAMPLES / "fig6.xml")
    ex = MissionExecutor(mission)
    v = Vehicle(ex)
    ex.start(0.0)
    v.run(0.0, 200.0)
    assert ex.state is State.COMPLETED
    assert [r.result for r in ex.results] == ["succeeded"] * len(mission.actions)
    assert v.photos == ["down", "down"] and v.landed and not v.armed
    kinds = events(v)
    assert kinds[0] is EventKind.MISSION_STARTED and kinds[-1] is EventKind.MISSION_COMPLETED
    assert kinds.count(EventKind.ACTION_SUCCEEDED) == len(mission.actions)
    move = next(r for r in ex.results if r.action_id == "move-2m")
    assert move.T_ned_body_goal is not None
    assert np.allclose(move.T_ned_body_goal[:3, 3], [2.0, 0.0, -1.0], atol=0.16)
    hovers = [r for r in ex.results if r.action == "hover"]
    assert all(r.seconds == pytest.approx(5.0, abs=0.11) for r in hovers)
    home = next(r for r in ex.results if r.action == "home")
    assert home.T_ned_body_goal is not None and np.allclose(home.T_ned_body_goal[:2, 3], [0.0, 0.0])
    last = v.outputs[-1]
    assert last.goal is None and not last.hold and last.progress is None
    # Smooth across action changes: no velocity jump beyond the acceleration limit (1 m/s^2 * 0.1 s).
    v_cmd = np.array([[c.vx_m_s, c.vy_m_s, c.vz_m_s] for c in v.commands])
    assert np.linalg.norm(np.diff(v_cmd, axis=0), axis=1).max() <= 0.1 + 1e-9


def test_progress_reports_action_distance_and_eta() -> None:
    mission = parse_mission(doc('<gotoxy id="far" x="4" y="0" speed="0.5"/>'))
    ex = MissionExecutor(mission)
    ex.start(0.0)
    out = ex.step(0.0, NavSnapshot(0.0, pose(0, 0, -2), armed=True, landed=False))
    assert out.goal is not None and np.allclose(out.goal.T_ned_body_goal[:3, 3], [4.0, 0.0, -2.0])
    assert out.progress is not None
    assert (out.progress.index, out.progress.count, out.progress.action, out.progress.action_id) == (0, 1, "gotoxy",
                                                                                                     "far")
    assert out.progress.distance_m == pytest.approx(4.0) and out.progress.eta_s == pytest.approx(8.0)
    assert out.progress.text() == "action 1/1 gotoxy far: 4.00 m, yaw +0 deg, ETA 8.0 s"


def test_timeout_aborts_and_holds() -> None:
    mission = parse_mission(doc('<gotoxy id="g" x="50" y="0" timeout="5"/>\n<land/>'))
    ex = MissionExecutor(mission)
    v = Vehicle(ex, pose(0, 0, -2), armed=True, landed=False)
    ex.start(0.0)
    t = v.run(0.0, 30.0)
    assert ex.state is State.FAILED
    assert t == pytest.approx(5.2, abs=0.11)
    result = ex.results[-1]
    assert (result.action_id, result.result) == ("g", "timeout") and "timed out after 5 s" in result.message
    last = v.outputs[-1]
    assert last.state is State.FAILED and last.hold and last.goal is None
    assert last.request is not None and last.request.kind is RequestKind.HOLD
    assert EventKind.ACTION_FAILED in events(v) and EventKind.MISSION_FAILED in events(v)
    assert len(ex.results) == 1  # land never started
    out = ex.step(t + 1.0, v.nav(t + 1.0))
    assert out.state is State.FAILED and out.hold and out.request is None


def test_failed_photo_aborts_the_mission() -> None:
    mission = parse_mission(doc('<take-photo id="p" camera="down"/>\n<land/>'))
    ex = MissionExecutor(mission)
    v = Vehicle(ex, pose(0, 0, -2), armed=True, landed=False, photo_ok=False)
    ex.start(0.0)
    v.run(0.0, 5.0)
    assert ex.state is State.FAILED
    assert ex.results[-1].result == "failed" and "camera unplugged" in ex.results[-1].message


def test_pause_freezes_timers_and_resume_continues() -> None:
    mission = parse_mission(doc('<hover id="h" seconds="4" timeout="5"/>'))
    ex = MissionExecutor(mission)
    nav = NavSnapshot(0.0, pose(1, 2, -3, 0.5), armed=True, landed=False)
    ex.start(0.0)
    out = ex.step(0.0, nav)
    assert out.goal is not None and np.allclose(out.goal.T_ned_body_goal, pose(1, 2, -3, 0.5))
    ex.step(2.0, nav)
    ex.pause(2.0)
    out = ex.step(2.1, nav)
    assert out.state is State.PAUSED and out.hold and out.goal is None
    assert out.request is not None and out.request.kind is RequestKind.HOLD
    assert [e.kind for e in out.events] == [EventKind.MISSION_PAUSED, EventKind.REQUEST]
    out = ex.step(60.0, nav)  # a long pause must not time the action out
    assert out.state is State.PAUSED and out.progress is not None and out.progress.elapsed_s == pytest.approx(2.0)
    ex.resume(60.0)
    out = ex.step(60.0, nav)
    assert out.state is State.RUNNING and out.goal is not None and out.request is None
    assert ex.step(61.9, nav).state is State.RUNNING  # 3.9 s of hovering so far
    out = ex.step(62.0, nav)
    assert out.state is State.COMPLETED
    assert ex.results[0].result == "succeeded"


def test_resume_before_step_drops_the_undelivered_hold() -> None:
    ex = MissionExecutor(parse_mission(doc('<hover seconds="4"/>')))
    nav = NavSnapshot(0.0, pose(0, 0, -2), armed=True, landed=False)
    ex.start(0.0)
    ex.step(0.0, nav)
    ex.pause(1.0)
    ex.resume(1.5)
    out = ex.step(1.6, nav)
    assert out.request is None and out.state is State.RUNNING


def test_abort_holds_and_invalid_transitions_raise() -> None:
    ex = MissionExecutor(parse_mission(doc('<hover seconds="4"/>')))
    nav = NavSnapshot(0.0, pose(0, 0, -2), armed=True, landed=False)
    with pytest.raises(MissionError, match="cannot pause: mission is idle"):
        ex.pause(0.0)
    with pytest.raises(MissionError, match="cannot abort"):
        ex.abort(0.0)
    assert ex.step(0.0, nav).state is State.IDLE
    ex.start(0.0)
    with pytest.raises(MissionError, match="cannot start"):
        ex.start(0.0)
    with pytest.raises(MissionError, match="cannot resume"):
        ex.resume(0.0)
    ex.step(0.5, nav)
    ex.abort(1.0, "battery low")
    out = ex.step(1.1, nav)
    assert out.state is State.ABORTED and out.hold and out.goal is None
    assert out.request is not None and out.request.kind is RequestKind.HOLD
    assert any(e.kind is EventKind.MISSION_ABORTED and "battery low" in e.message for e in out.events)
    assert ex.results[0].result == "aborted"
    with pytest.raises(MissionError, match="cannot abort: mission is aborted"):
        ex.abort(2.0)


def test_success_needs_the_settle_time_inside_the_thresholds() -> None:
    mission = parse_mission(doc('<gotoxy x="1" y="0" yaw="0" threshold="0.1" yaw-threshold="5"/>',
                                'name="t" frame="ned" settle="1.0"'))
    ex = MissionExecutor(mission)
    ex.start(0.0)

    def nav(x: float, yaw_deg: float = 0.0) -> NavSnapshot:
        return NavSnapshot(0.0, pose(x, 0, -2, math.radians(yaw_deg)), armed=True, landed=False)

    ex.step(0.0, nav(0.0))
    ex.step(1.0, nav(0.95))  # inside
    ex.step(1.5, nav(0.8))  # leaves: settle timer resets
    ex.step(2.0, nav(0.95))
    assert ex.step(2.9, nav(0.95)).state is State.RUNNING
    ex.step(3.0, nav(0.95, yaw_deg=8.0))  # yaw outside its threshold
    ex.step(3.1, nav(0.95))
    assert ex.step(4.0, nav(0.95)).state is State.RUNNING
    assert ex.step(4.1, nav(0.95)).state is State.COMPLETED


def test_no_success_and_no_goal_without_a_valid_pose() -> None:
    ex = MissionExecutor(parse_mission(doc('<gotoxy x="0" y="0" timeout="3"/>')))
    ex.start(0.0)
    lost = NavSnapshot(0.0, pose(0, 0, -2), ok=False, armed=True, landed=False)
    out = ex.step(0.0, lost)
    assert out.goal is None and out.state is State.RUNNING
    assert ex.step(2.0, lost).state is State.RUNNING
    out = ex.step(2.1, NavSnapshot(2.1, pose(0, 0, -2), armed=True, landed=False))
    assert out.goal is not None
    assert ex.step(3.2, lost).state is State.FAILED


def test_notify_ignores_stale_or_unknown_requests() -> None:
    ex = MissionExecutor(parse_mission(doc('<take-photo camera="c"/>')))
    nav = NavSnapshot(0.0, pose(0, 0, -2), armed=True, landed=False)
    ex.start(0.0)
    out = ex.step(0.0, nav)
    assert out.request is not None and out.request.kind is RequestKind.PHOTO and out.request.camera == "c"
    assert ex.pending_request == out.request and out.pending_request == out.request
    assert not ex.notify(out.request.id + 100, True)
    assert ex.notify(out.request.id, True, 0.5)
    assert not ex.notify(out.request.id, True, 0.6)
    assert ex.step(0.7, nav).state is State.COMPLETED


def test_takeoff_arms_then_takes_off_then_climbs() -> None:
    ex = MissionExecutor(parse_mission(doc('<takeoff height="2" threshold="0.1"/>')))
    v = Vehicle(ex, pose(3.0, 4.0, 0.0))
    ex.start(0.0)
    v.run(0.0, 30.0)
    assert ex.state is State.COMPLETED
    kinds = [out.request.kind for out in v.outputs if out.request is not None]
    assert kinds[:2] == [RequestKind.ARM, RequestKind.TAKEOFF]
    takeoff_req = next(o.request for o in v.outputs if o.request is not None and o.request.kind is RequestKind.TAKEOFF)
    assert takeoff_req.height_m == 2.0
    assert v.T[2, 3] == pytest.approx(-2.0, abs=0.1) and np.allclose(v.T[:2, 3], [3.0, 4.0], atol=1e-6)
    assert kinds[-1] is RequestKind.HOLD  # completed in the air: hold


def test_takeoff_when_already_flying_is_a_climb_and_arm_refusal_fails() -> None:
    ex = MissionExecutor(parse_mission(doc('<takeoff height="2"/>')))
    ex.start(0.0)
    out = ex.step(0.0, NavSnapshot(0.0, pose(0, 0, -1.0), armed=True, landed=False,
                                   home_T_ned_body=pose(0, 0, 0.5)))
    assert out.request is None and out.goal is not None
    assert out.goal.T_ned_body_goal[2, 3] == pytest.approx(0.5 - 2.0)  # height above the given home

    ex = MissionExecutor(parse_mission(doc('<takeoff height="2"/>')))
    ex.start(0.0)
    out = ex.step(0.0, NavSnapshot(0.0, pose(0, 0, 0)))
    assert out.request is not None and out.request.kind is RequestKind.ARM
    ex.notify(out.request.id, False, 0.1, "PreArm: compass not calibrated")
    assert ex.step(0.2, NavSnapshot(0.2, pose(0, 0, 0))).state is State.FAILED
    assert "arm failed: PreArm" in ex.results[0].message


def test_a_pause_during_the_take_off_request_climbs_with_the_servo_after_the_resume() -> None:
    """The pause's hold supersedes the take-off request (the daemon cancels it, no answer ever comes): resumed in
    the air the action climbs with the servo, resumed still on the ground it asks for the take-off again."""
    for airborne in (True, False):
        ex = MissionExecutor(parse_mission(doc('<takeoff height="2" threshold="0.1" timeout="30"/>')))
        ex.start(0.0)
        ground = NavSnapshot(0.0, pose(0, 0, 0), armed=True, landed=True)
        out = ex.step(0.0, ground)
        assert out.request is not None and out.request.kind is RequestKind.TAKEOFF
        ex.pause(1.0)  # e.g. a vision-loss brake half-way up; the take-off request is never answered
        assert ex.step(1.1, ground).request.kind is RequestKind.HOLD  # type: ignore[union-attr]
        ex.resume(2.0)
        now = NavSnapshot(2.0, pose(0, 0, -0.8), armed=True, landed=False) if airborne else ground
        out = ex.step(2.0, now)
        if airborne:
            assert out.request is None and out.goal is not None
            assert out.goal.T_ned_body_goal[2, 3] == pytest.approx(-2.0)
            states = [ex.step(t, NavSnapshot(t, pose(0, 0, -2.0), armed=True, landed=False)).state
                      for t in np.arange(2.1, 5.0, 0.1)]
            assert states[-1] is State.COMPLETED and ex.results[0].result == "succeeded"
        else:
            assert out.request is not None and out.request.kind is RequestKind.TAKEOFF and out.goal is None
            assert ex.pending_request is out.request


def test_rack_frame_goals_go_through_T_ned_rack() -> None:
    rack = '<rack length="10"><pipe radius="0.15" gap="0.1"/><pipe radius="0.2" gap="0.1"/><pipe radius="0.15"/></rack>'
    body = '<gotoxy x="1.0" y="5.0" yaw="0"/>\n<gotoz z="2.5"/>\n<servo pipe="2" height="2.0" y="4.0" yaw="90"/>'
    mission = parse_mission(doc(body, 'name="r" frame="rack"', rack))
    T_ned_rack = default_T_ned_rack()
    T_ned_rack[:3, 3] = [10.0, -5.0, 0.5]  # rack origin 10 m north, 5 m west, support plane 0.5 m below home
    ex = MissionExecutor(mission, T_ned_rack=T_ned_rack)
    ex.start(0.0)
    T = pose(12.0, -3.0, -1.5, 0.3)
    out = ex.step(0.0, NavSnapshot(0.0, T, armed=True, landed=False))
    assert out.goal is not None
    # rack (x=1, y=5) -> north = 10 + 5, east = -5 + 1; height kept; rack yaw 0 = along rack +y = north.
    assert np.allclose(out.goal.T_ned_body_goal[:3, 3], [15.0, -4.0, -1.5])
    assert float(yaw_from_rotation(out.goal.T_ned_body_goal[:3, :3])) == pytest.approx(0.0, abs=1e-12)
    ex.step(0.1, NavSnapshot(0.1, out.goal.T_ned_body_goal, armed=True, landed=False))
    out = ex.step(0.7, NavSnapshot(0.7, out.goal.T_ned_body_goal, armed=True, landed=False))
    assert out.goal is not None and out.progress is not None and out.progress.action == "gotoz"
    assert np.allclose(out.goal.T_ned_body_goal[:3, 3], [15.0, -4.0, 0.5 - 2.5])  # rack z up -> NED down
    ex.step(0.8, NavSnapshot(0.8, out.goal.T_ned_body_goal, armed=True, landed=False))
    out = ex.step(1.4, NavSnapshot(1.4, out.goal.T_ned_body_goal, armed=True, landed=False))
    assert out.goal is not None and out.progress is not None and out.progress.action == "servo"
    # pipe 2 axis at x = 0.3 + 0.1 + 0.2 = 0.6, top at z = 0.4; goal 2.0 m above the top.
    assert np.allclose(out.goal.T_ned_body_goal[:3, 3], [10.0 + 4.0, -5.0 + 0.6, 0.5 - 2.4])
    # rack yaw 90 deg = nose along rack +x = east = NED yaw +90 deg.
    assert float(yaw_from_rotation(out.goal.T_ned_body_goal[:3, :3])) == pytest.approx(math.pi / 2)


def test_servo_needs_a_rack_layout() -> None:
    mission = parse_mission(doc('<servo pipe="2" height="2.0" y="4.0"/>'))
    with pytest.raises(MissionError, match=r"<string>:3: servo\.pipe: servo actions need a rack layout"):
        MissionExecutor(mission)
    with pytest.raises(MissionError, match="pipe 2 does not exist"):
        MissionExecutor(mission, rack=RackLayout(radii_m=(0.1,), gaps_m=(), length_m=10.0))
    ex = MissionExecutor(mission, rack=RackLayout(radii_m=(0.1, 0.2), gaps_m=(0.3,), length_m=10.0))
    assert ex.rack is not None and ex.rack.pipe_axis_x_m(2) == pytest.approx(0.7)
    # A rack from outside the file is checked like a declared one: goal height and y before flight.
    high = parse_mission(doc('<servo pipe="2" height="9.0" y="4.0"/>'))  # passes the parser (pipe top unknown)
    with pytest.raises(MissionError, match=r"<string>:3: servo\.height: goal height 10\.4 m .* above the ceiling 10 m"):
        MissionExecutor(high, rack=RackLayout(radii_m=(0.1, 0.7), gaps_m=(0.3,), length_m=10.0))
    with pytest.raises(MissionError, match=r"servo\.y: 4 m is off the pipes \(0\.\.3 m\)"):
        MissionExecutor(mission, rack=RackLayout(radii_m=(0.1, 0.2), gaps_m=(0.3,), length_m=3.0))


def test_rack_sweep_completes_in_the_loop() -> None:
    mission = load_mission(EXAMPLES / "rack_sweep.xml")
    T_ned_rack = default_T_ned_rack()
    ex = MissionExecutor(mission, T_ned_rack=T_ned_rack)
    v = Vehicle(ex, pose(0.0, 1.0, 0.0))
    ex.start(0.0)
    v.run(0.0, 600.0, dt=0.2)
    assert ex.state is State.COMPLETED, ex.results[-1]
    assert len(v.photos) == 6


def test_gotoz_z_and_height_in_ned() -> None:
    mission = parse_mission(doc('<gotoz z="-3.0"/>\n<gotoz height="1.5"/>'))
    ex = MissionExecutor(mission)
    ex.start(0.0)
    home = pose(0.0, 0.0, 0.2)
    T = pose(1.0, 2.0, -2.0, 0.7)
    out = ex.step(0.0, NavSnapshot(0.0, T, armed=True, landed=False, home_T_ned_body=home))
    assert out.goal is not None and np.allclose(out.goal.T_ned_body_goal, pose(1.0, 2.0, -3.0, 0.7))
    goal = out.goal.T_ned_body_goal
    ex.step(0.1, NavSnapshot(0.1, goal, armed=True, landed=False))
    out = ex.step(0.7, NavSnapshot(0.7, goal, armed=True, landed=False))
    assert out.goal is not None and out.progress is not None and out.progress.index == 1
    assert np.allclose(out.goal.T_ned_body_goal, pose(1.0, 2.0, 0.2 - 1.5, 0.7))  # 1.5 m above the given home
    assert ex.home_T_ned_body is not None and np.allclose(ex.home_T_ned_body, home)


def test_along_pipe_goals_wait_for_the_along_pipe_position_with_their_timers_frozen() -> None:
    rack = '<rack length="10"><pipe radius="0.15" gap="0.1"/><pipe radius="0.2" gap="0.1"/><pipe radius="0.15"/></rack>'
    body = '<gotoz id="z" z="2.5"/>\n<servo id="s" pipe="2" height="2.0" y="4.0" yaw="0" timeout="5"/>'
    mission = parse_mission(doc(body, 'name="r" frame="rack"', rack))
    ex = MissionExecutor(mission)
    ex.start(0.0)
    T = default_T_ned_rack() @ pose(0.6, 1.0, 2.5)  # at the gotoz height: it is reached after the settle time

    def nav(t: float, known: bool) -> NavSnapshot:
        return NavSnapshot(t, T, armed=True, landed=False, along_pipe_known=known)

    out = ex.step(0.0, nav(0.0, False))  # gotoz needs no along-pipe position: it goes on
    assert out.goal is not None and not out.needs_along_pipe
    out = ex.step(0.5, nav(0.5, False))  # gotoz settled; the servo waits
    assert out.progress is not None and out.progress.action_id == "s"
    assert out.goal is None and out.needs_along_pipe and out.state is State.RUNNING
    assert EventKind.ACTION_WAITING in [e.kind for e in out.events]
    out = ex.step(30.0, nav(30.0, False))  # far beyond the servo's 5 s timeout: still waiting, not failed
    assert out.state is State.RUNNING and out.needs_along_pipe and out.goal is None and out.events == ()
    ex.pause(30.0)
    out = ex.step(31.0, nav(31.0, False))
    assert out.state is State.PAUSED and not out.needs_along_pipe
    ex.resume(40.0)
    out = ex.step(41.0, nav(41.0, True))
    assert out.goal is not None and not out.needs_along_pipe
    assert EventKind.ACTION_CONTINUED in [e.kind for e in out.events]
    assert out.progress is not None and out.progress.elapsed_s == pytest.approx(0.0)  # the wait is not counted
    assert ex.step(45.9, nav(45.9, True)).state is State.RUNNING
    out = ex.step(46.2, nav(46.2, True))  # 5 s after the wait ended: the servo's own timeout
    assert out.state is State.FAILED and ex.results[-1].result == "timeout"


def test_a_known_along_pipe_position_changes_nothing_and_an_unknown_one_stops_after_the_take_off() -> None:
    mission = load_mission(EXAMPLES / "fig6.xml")
    runs = []
    for known in (True, False):
        ex = MissionExecutor(mission)
        v = Vehicle(ex)
        v.nav = lambda t, v=v, known=known: NavSnapshot(  # type: ignore[method-assign]
            stamp_s=t, T_ned_body=v.T, ok=v.ok, armed=v.armed, landed=v.landed, along_pipe_known=known)
        ex.start(0.0)
        v.run(0.0, 200.0 if known else 60.0)
        runs.append((ex, v))
    (ex_known, v_known), (ex_unknown, v_unknown) = runs
    assert ex_known.state is State.COMPLETED and not any(o.needs_along_pipe for o in v_known.outputs)
    # unknown: armed and taken off (the autopilot's take-off needs no position), then the climb waits
    assert ex_unknown.state is State.RUNNING and ex_unknown.results == ()
    assert v_unknown.armed and not v_unknown.landed and v_unknown.commands == []
    last = v_unknown.outputs[-1]
    assert last.needs_along_pipe and last.goal is None and last.progress is not None
    assert last.progress.action == "takeoff" and last.progress.elapsed_s == pytest.approx(0.2)  # arm, take off
