"""Parsing the mission's `<rack>` declaration and each action element into its `companion.mission.model`
dataclass (`companion.mission.parser`, step 5)."""

from __future__ import annotations

from companion.mission.model import (
    Action,
    Frame,
    GotoXY,
    GotoZ,
    Home,
    Hover,
    Land,
    RackLayout,
    Servo,
    Takeoff,
    TakePhoto,
)
from companion.mission.parser_fields import _Checker, _Element


class _Defaults:
    def __init__(self, timeout_s: float, speed_m_s: float, threshold_m: float, yaw_threshold_rad: float) -> None:
        self.timeout_s = timeout_s
        self.speed_m_s = speed_m_s
        self.threshold_m = threshold_m
        self.yaw_threshold_rad = yaw_threshold_rad


def _parse_rack(e: _Element, source: str) -> RackLayout:
    length_m = e.required("length")
    e.check("length", 0.0 < length_m <= 1000.0, f"{length_m:g} m must be in (0, 1000] m")
    pipes = [_Element(p, source) for p in e.elem if isinstance(p.tag, str)]
    radii: list[float] = []
    gaps: list[float] = []
    for k, p in enumerate(pipes):
        r = p.required("radius")
        p.check("radius", 0.0 < r <= 5.0, f"{r:g} m must be in (0, 5] m")
        radii.append(r)
        gap = p.number("gap")
        if k < len(pipes) - 1:
            if gap is None:
                raise p.error("gap", "required on every pipe but the last (surface-to-surface gap to the next pipe)")
            p.check("gap", 0.0 <= gap <= 100.0, f"{gap:g} m must be in [0, 100] m")
            gaps.append(gap)
        elif gap is not None:
            raise p.error("gap", "the last pipe has no next pipe: remove its gap")
    return RackLayout(radii_m=tuple(radii), gaps_m=tuple(gaps), length_m=length_m)


def _parse_action(
    e: _Element, index: int, frame: Frame, d: _Defaults, c: _Checker, rack: RackLayout | None
) -> Action:
    action_id = e.text("id") or f"{index + 1}-{e.tag}"
    timeout_s = c.timeout(e, e.number_or("timeout", d.timeout_s)) if e.has("timeout") else d.timeout_s

    def speed() -> float:
        return c.speed(e, e.number_or("speed", d.speed_m_s)) if e.has("speed") else d.speed_m_s

    def threshold() -> float:
        return c.threshold(e, e.number_or("threshold", d.threshold_m)) if e.has("threshold") else d.threshold_m

    def yaw_threshold() -> float:
        if not e.has("yaw-threshold"):
            return d.yaw_threshold_rad
        return c.yaw_threshold_deg(e, e.required("yaw-threshold"))

    if e.tag == "takeoff":
        height_m = c.height(e, e.required("height"), "height")
        return Takeoff(line=e.line, id=action_id, timeout_s=timeout_s, height_m=height_m, threshold_m=threshold())
    if e.tag == "gotoxy":
        yaw = e.number("yaw")
        return GotoXY(
            line=e.line, id=action_id, timeout_s=timeout_s,
            x_m=c.horizontal(e, e.required("x"), "x"),
            y_m=c.horizontal(e, e.required("y"), "y"),
            yaw_rad=None if yaw is None else c.yaw_deg(e, yaw),
            speed_m_s=speed(),
            threshold_m=threshold(),
            yaw_threshold_rad=yaw_threshold(),
        )
    if e.tag == "gotoz":
        z, height = e.number("z"), e.number("height")
        if (z is None) == (height is None):
            raise e.error("z" if z is not None else "height", "give exactly one of 'z' or 'height'")
        if z is not None:
            up_m = -z if frame is Frame.NED else z
            c.height(e, up_m, "z", label=f"z {z:g} m ({frame.value} frame, a height of {up_m:g} m)")
        if height is not None:
            c.height(e, height, "height")
        return GotoZ(
            line=e.line, id=action_id, timeout_s=timeout_s, z_m=z, height_m=height, speed_m_s=speed(),
            threshold_m=threshold(),
        )
    if e.tag == "take-photo":
        return TakePhoto(line=e.line, id=action_id, timeout_s=timeout_s, camera=e.text("camera") or "")
    if e.tag == "hover":
        seconds = e.required("seconds")
        e.check("seconds", 0.0 < seconds <= c.limits.max_hover_s,
                f"{seconds:g} s must be in (0, {c.limits.max_hover_s:g}] s")
        if e.has("timeout"):
            e.check("timeout", timeout_s > seconds, f"{timeout_s:g} s must be longer than the hover ({seconds:g} s)")
        else:
            timeout_s = seconds + d.timeout_s
        return Hover(line=e.line, id=action_id, timeout_s=timeout_s, duration_s=seconds)
    if e.tag == "servo":
        pipe_text = e.text("pipe") or ""
        try:
            pipe = int(pipe_text)
        except ValueError:
            raise e.error("pipe", f"'{pipe_text[:40]}' is not a pipe index") from None
        height = e.required("height")
        y = c.horizontal(e, e.required("y"), "y")
        yaw = e.number_or("yaw", 0.0)
        if rack is not None:
            e.check("pipe", 1 <= pipe <= rack.count, f"pipe {pipe} does not exist (the rack has {rack.count} pipes)")
            e.check("y", 0.0 <= y <= rack.length_m, f"{y:g} m is off the pipes (0..{rack.length_m:g} m)")
            top = rack.pipe_top_z_m(pipe)
            c.height(e, height, "height", label=f"height above the pipe {height:g} m")
            label = f"goal height {top + height:g} m (pipe top {top:g} m + {height:g} m)"
            c.height(e, top + height, "height", label=label)
        else:
            c.height(e, height, "height", label=f"height above the pipe {height:g} m")
        return Servo(
            line=e.line, id=action_id, timeout_s=timeout_s,
            pipe=pipe,
            height_m=height,
            y_m=y,
            yaw_rad=c.yaw_deg(e, yaw),
            speed_m_s=speed(),
            threshold_m=threshold(),
            yaw_threshold_rad=yaw_threshold(),
        )
    if e.tag == "home":
        return Home(line=e.line, id=action_id, timeout_s=timeout_s, speed_m_s=speed(), threshold_m=threshold())
    if e.tag == "land":
        return Land(line=e.line, id=action_id, timeout_s=timeout_s)
    raise e.error(None, "unknown action")  # unreachable after the schema
