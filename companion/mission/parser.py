"""Hardened mission XML parser: size and encoding checks, no DTD/entities/PIs, XSD, then range checks.

Order of the checks (each failure raises `MissionError` "SOURCE:LINE: element.attribute: message"):
1. size (at most `MAX_MISSION_BYTES`) and strict UTF-8;
2. any DOCTYPE/ENTITY/ELEMENT/ATTLIST/NOTATION declaration or processing instruction is
   refused before the XML parser sees the text (this is what stops billion-laughs bombs and
   external entities such as file:///etc/passwd or http://...);
3. well-formedness with lxml configured with resolve_entities=False, no_network=True,
   load_dtd=False, huge_tree=False (defence in depth behind step 2);
4. the XML Schema `missions/mission.xsd` (embedded as `companion.mission.schema.MISSION_XSD`);
5. semantic and range checks against `MissionLimits` (speed, ceiling, geofence, timeouts,
   thresholds, rack pipe indices, unique ids).
"""

from __future__ import annotations

import math
import os
import re
import threading
from pathlib import Path
from typing import Any

from lxml import etree

from companion.errors import MissionError
from companion.mission.model import (
    Action,
    Frame,
    GotoXY,
    GotoZ,
    Home,
    Hover,
    Land,
    Mission,
    MissionLimits,
    RackLayout,
    Servo,
    Takeoff,
    TakePhoto,
)
from companion.mission.schema import MISSION_XSD
from companion.mission.site import check_geofence

__all__ = [
    "DEFAULT_SETTLE_S",
    "DEFAULT_SPEED_M_S",
    "DEFAULT_THRESHOLD_M",
    "DEFAULT_TIMEOUT_S",
    "DEFAULT_YAW_THRESHOLD_DEG",
    "MAX_MISSION_BYTES",
    "load_mission",
    "parse_mission",
    "validate_cli",
]

MAX_MISSION_BYTES = 1 << 20  # 1 MiB
DEFAULT_TIMEOUT_S = 60.0
DEFAULT_SPEED_M_S = 0.5
DEFAULT_THRESHOLD_M = 0.2
DEFAULT_YAW_THRESHOLD_DEG = 5.0
DEFAULT_SETTLE_S = 0.5

_FORBIDDEN_DECL = re.compile(rb"<!\s*(DOCTYPE|ENTITY|ELEMENT|ATTLIST|NOTATION)", re.IGNORECASE)
_PI = re.compile(rb"<\?([^\s?>]*)")
_ENCODING_DECL = re.compile(rb"""^<\?xml[^>]*?\bencoding\s*=\s*["']([^"']*)["']""")
_XSD_MESSAGE = re.compile(r"^Element '([^']+)'(?:, attribute '([^']+)')?: (.*)$", re.DOTALL)
_REQUIRED_ATTR = re.compile(r"The attribute '([^']+)' is required but missing")
_BOM = b"\xef\xbb\xbf"

_schema: etree.XMLSchema | None = None
_schema_lock = threading.Lock()  # XMLSchema.error_log is per object: validate one document at a time


def _get_schema() -> etree.XMLSchema:
    global _schema
    if _schema is None:
        parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False)
        _schema = etree.XMLSchema(etree.fromstring(MISSION_XSD.encode("utf-8"), parser))
    return _schema


def _hardened_parser() -> etree.XMLParser:
    return etree.XMLParser(
        resolve_entities=False,
        no_network=True,
        load_dtd=False,
        dtd_validation=False,
        huge_tree=False,
        remove_comments=True,
        remove_pis=False,
        collect_ids=False,
        encoding="utf-8",
    )


def _line_of(data: bytes, offset: int) -> int:
    return data.count(b"\n", 0, offset) + 1


def _check_raw(data: bytes, source: str) -> None:
    """Size, UTF-8, and no DTD / entity declarations / processing instructions."""
    if len(data) > MAX_MISSION_BYTES:
        raise MissionError(f"{source}: file is {len(data)} bytes, above the {MAX_MISSION_BYTES}-byte mission limit")
    if not data.strip():
        raise MissionError(f"{source}:1: mission: the file is empty")
    try:
        data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MissionError(
            f"{source}:{_line_of(data, exc.start)}: encoding: not valid UTF-8 at byte {exc.start}"
        ) from None
    nul = data.find(b"\x00")
    if nul >= 0:
        raise MissionError(f"{source}:{_line_of(data, nul)}: encoding: NUL byte in the file")
    m = _FORBIDDEN_DECL.search(data)
    if m is not None:
        kind = m.group(1).decode("ascii").upper()
        raise MissionError(
            f"{source}:{_line_of(data, m.start())}: {kind}: DTD and entity declarations are not allowed in "
            "mission files (no entity expansion, no external entities)"
        )
    body_start = len(_BOM) if data.startswith(_BOM) else 0
    for m in _PI.finditer(data):
        is_declaration = m.start() == body_start and m.group(1) == b"xml"
        if not is_declaration:
            target = m.group(1).decode("utf-8", "replace") or "?"
            raise MissionError(
                f"{source}:{_line_of(data, m.start())}: processing-instruction: '<?{target}' is not allowed "
                "in mission files (only the <?xml ...?> declaration on the first line)"
            )
    enc = _ENCODING_DECL.match(data[body_start:])
    if enc is not None and enc.group(1).decode("ascii", "replace").lower().replace("_", "-") not in ("utf-8", "utf8"):
        raise MissionError(
            f"{source}:1: encoding: declared encoding '{enc.group(1).decode('ascii', 'replace')}' is not supported, "
            "use UTF-8"
        )


def _parse_xml(data: bytes, source: str) -> etree._Element:
    try:
        root = etree.fromstring(data, _hardened_parser())
    except etree.XMLSyntaxError as exc:
        line = exc.lineno if exc.lineno else 1
        msg = str(exc.msg).split(", line ")[0] if exc.msg else "syntax error"
        raise MissionError(f"{source}:{line}: xml: not well-formed: {msg}") from None
    except (etree.LxmlError, ValueError) as exc:
        raise MissionError(f"{source}:1: xml: cannot parse: {exc}") from None
    if root is None:
        raise MissionError(f"{source}:1: xml: no root element")
    docinfo: Any = root.getroottree().docinfo
    if docinfo.doctype or docinfo.internalDTD is not None:
        raise MissionError(f"{source}:1: DOCTYPE: DTDs are not allowed in mission files")
    for node in [*root.itersiblings(preceding=True), *root.itersiblings(), *root.iter()]:
        if isinstance(node, etree._ProcessingInstruction):
            raise MissionError(f"{source}:{node.sourceline or 1}: processing-instruction: not allowed")
        if isinstance(node, etree._Entity):
            raise MissionError(f"{source}:{node.sourceline or 1}: entity: entity references are not allowed")
    return root


def _validate_schema(root: etree._Element, source: str) -> None:
    with _schema_lock:
        schema = _get_schema()
        if schema.validate(root):
            return
        errors: list[Any] = [*schema.error_log]  # type: ignore[misc]
    first = errors[0]
    more = f" (and {len(errors) - 1} more)" if len(errors) > 1 else ""
    m = _XSD_MESSAGE.match(first.message)
    if m is None:
        raise MissionError(f"{source}:{first.line}: schema: {first.message}{more}")
    element, attribute, text = m.group(1), m.group(2), m.group(3).strip()
    required = _REQUIRED_ATTR.search(text)
    if attribute is None and required is not None:
        attribute = required.group(1)
        text = "required attribute is missing"
    field = f"{element}.{attribute}" if attribute else element
    text = text.replace("the atomic type 'number'", "a plain decimal number (no exponent, no NaN/INF)")
    text = text.replace("the atomic type 'name'", "a name (letters, digits, '_', '.', '-')")
    text = text.replace("the atomic type 'pipeIndex'", "a pipe index (an integer 1..64)")
    raise MissionError(f"{source}:{first.line}: {field}: {text}{more}")


class _Element:
    """Attribute access of one element with errors naming the line and field."""

    def __init__(self, elem: etree._Element, source: str) -> None:
        self.elem = elem
        self.tag = str(elem.tag)
        line: Any = elem.sourceline
        self.line = int(line) if isinstance(line, int) and line > 0 else 1
        self.source = source

    def error(self, attribute: str | None, message: str) -> MissionError:
        field = f"{self.tag}.{attribute}" if attribute else self.tag
        return MissionError(f"{self.source}:{self.line}: {field}: {message}")

    def has(self, attribute: str) -> bool:
        return self.elem.get(attribute) is not None

    def text(self, attribute: str) -> str | None:
        value = self.elem.get(attribute)
        return None if value is None else str(value).strip()

    def number(self, attribute: str) -> float | None:
        raw = self.text(attribute)
        if raw is None:
            return None
        try:
            value = float(raw)
        except ValueError:
            raise self.error(attribute, f"'{raw[:40]}' is not a number") from None
        if not math.isfinite(value):
            raise self.error(attribute, f"'{raw[:40]}...' is out of the floating-point range")
        return value

    def number_or(self, attribute: str, default: float) -> float:
        value = self.number(attribute)
        return default if value is None else value

    def required(self, attribute: str) -> float:
        value = self.number(attribute)
        if value is None:
            raise self.error(attribute, "required attribute is missing")
        return value

    def check(self, attribute: str, ok: bool, message: str) -> None:
        if not ok:
            raise self.error(attribute, message)


class _Defaults:
    def __init__(self, timeout_s: float, speed_m_s: float, threshold_m: float, yaw_threshold_rad: float) -> None:
        self.timeout_s = timeout_s
        self.speed_m_s = speed_m_s
        self.threshold_m = threshold_m
        self.yaw_threshold_rad = yaw_threshold_rad


class _Checker:
    """Range checks shared by the header and the actions."""

    def __init__(self, limits: MissionLimits) -> None:
        self.limits = limits

    def speed(self, e: _Element, value: float, attribute: str = "speed") -> float:
        e.check(attribute, value > 0.0, f"{value:g} m/s must be > 0 m/s")
        e.check(
            attribute,
            value <= self.limits.max_speed_m_s,
            f"{value:g} m/s exceeds the vehicle limit {self.limits.max_speed_m_s:g} m/s",
        )
        return value

    def timeout(self, e: _Element, value: float, attribute: str = "timeout") -> float:
        e.check(attribute, value > 0.0, f"{value:g} s must be > 0 s")
        e.check(
            attribute,
            value <= self.limits.max_timeout_s,
            f"{value:g} s exceeds the limit {self.limits.max_timeout_s:g} s",
        )
        return value

    def threshold(self, e: _Element, value: float, attribute: str = "threshold") -> float:
        lo, hi = self.limits.min_threshold_m, self.limits.max_threshold_m
        e.check(attribute, lo <= value <= hi, f"{value:g} m is outside the allowed range {lo:g}..{hi:g} m")
        return value

    def yaw_threshold_deg(self, e: _Element, value_deg: float, attribute: str = "yaw-threshold") -> float:
        lo = math.degrees(self.limits.min_yaw_threshold_rad)
        hi = math.degrees(self.limits.max_yaw_threshold_rad)
        e.check(
            attribute, lo - 1e-9 <= value_deg <= hi + 1e-9,
            f"{value_deg:g} deg is outside the allowed range {lo:g}..{hi:g} deg",
        )
        return math.radians(value_deg)

    def height(self, e: _Element, value: float, attribute: str, label: str | None = None) -> float:
        """Check a height above home / the rack plane (m, up); `label` describes it in messages."""
        lo, hi = self.limits.min_height_m, self.limits.ceiling_m
        label = label if label is not None else f"height {value:g} m"
        e.check(attribute, value <= hi, f"{label} is above the ceiling {hi:g} m")
        e.check(attribute, value >= lo, f"{label} is below the minimum flight height {lo:g} m")
        return value

    def horizontal(self, e: _Element, value: float, attribute: str) -> float:
        hi = self.limits.max_horizontal_m
        e.check(attribute, abs(value) <= hi, f"{value:g} m is outside the geofence +-{hi:g} m")
        return value

    def yaw_deg(self, e: _Element, value_deg: float, attribute: str = "yaw") -> float:
        e.check(attribute, abs(value_deg) <= 360.0, f"{value_deg:g} deg is outside -360..360 deg")
        return math.radians(value_deg)


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


def _build_mission(root: etree._Element, source: str, limits: MissionLimits) -> Mission:
    h = _Element(root, source)
    c = _Checker(limits)
    frame = Frame(h.text("frame") or "")
    timeout_s = c.timeout(h, h.number_or("timeout", DEFAULT_TIMEOUT_S))
    speed_m_s = c.speed(h, h.number_or("speed", min(DEFAULT_SPEED_M_S, limits.max_speed_m_s)))
    threshold_m = c.threshold(h, h.number_or("threshold", DEFAULT_THRESHOLD_M))
    yaw_threshold_rad = c.yaw_threshold_deg(h, h.number_or("yaw-threshold", DEFAULT_YAW_THRESHOLD_DEG))
    settle_s = h.number_or("settle", DEFAULT_SETTLE_S)
    h.check(
        "settle", 0.0 <= settle_s <= limits.max_settle_s, f"{settle_s:g} s must be in [0, {limits.max_settle_s:g}] s"
    )
    defaults = _Defaults(timeout_s, speed_m_s, threshold_m, yaw_threshold_rad)

    children = [_Element(child, source) for child in root if isinstance(child.tag, str)]
    rack: RackLayout | None = None
    if children and children[0].tag == "rack":
        rack = _parse_rack(children[0], source)
        children = children[1:]
    if len(children) > limits.max_actions:
        raise children[limits.max_actions].error(
            None, f"too many actions ({len(children)}, the limit is {limits.max_actions})"
        )
    actions: list[Action] = []
    first_line: dict[str, int] = {}
    for index, e in enumerate(children):
        action = _parse_action(e, index, frame, defaults, c, rack)
        if action.id in first_line:
            raise e.error("id", f"duplicate id '{action.id}' (first used on line {first_line[action.id]})")
        first_line[action.id] = action.line
        actions.append(action)
    mission = Mission(
        name=h.text("name") or "",
        frame=frame,
        timeout_s=timeout_s,
        speed_m_s=speed_m_s,
        threshold_m=threshold_m,
        yaw_threshold_rad=yaw_threshold_rad,
        settle_s=settle_s,
        limits=limits,
        rack=rack,
        actions=tuple(actions),
        source_name=source,
    )
    check_geofence(mission)  # the configured site box, the same line offline and at upload
    return mission


def parse_mission(
    text_or_bytes: str | bytes, source_name: str = "<string>", limits: MissionLimits | None = None
) -> Mission:
    """Validate and parse a mission document; raise `MissionError` "SOURCE:LINE: field: message"."""
    if isinstance(text_or_bytes, str):
        data = text_or_bytes.encode("utf-8", "surrogatepass")
    elif isinstance(text_or_bytes, bytes | bytearray | memoryview):
        data = bytes(text_or_bytes)
    else:
        raise MissionError(f"{source_name}: expected str or bytes, got {type(text_or_bytes).__name__}")
    limits = limits if limits is not None else MissionLimits()
    try:
        _check_raw(data, source_name)
        root = _parse_xml(data, source_name)
        _validate_schema(root, source_name)
        return _build_mission(root, source_name, limits)
    except MissionError as exc:
        raise MissionError(_one_line(str(exc))) from None


def _one_line(message: str, max_chars: int = 300) -> str:
    """Collapse whitespace (libxml2 quotes document fragments with newlines) and bound the length."""
    text = " ".join(message.split())
    return text if len(text) <= max_chars else text[: max_chars - 3] + "..."


def load_mission(path: str | os.PathLike[str], limits: MissionLimits | None = None) -> Mission:
    """Read, validate and parse the mission file at `path` (see `parse_mission`)."""
    source = os.fspath(path)
    try:
        with Path(source).open("rb") as f:
            data = f.read(MAX_MISSION_BYTES + 1)
    except OSError as exc:
        raise MissionError(f"{source}: cannot read the mission file: {exc.strerror or exc}") from None
    if len(data) > MAX_MISSION_BYTES:
        raise MissionError(f"{source}: file is larger than the {MAX_MISSION_BYTES}-byte mission limit")
    return parse_mission(data, source_name=source, limits=limits)


def validate_cli(path: str | os.PathLike[str], limits: MissionLimits | None = None) -> tuple[int, str]:
    """For `companion mission validate FILE`: (0, "FILE: valid: ...") or (2, "FILE:LINE: field: message")."""
    try:
        mission = load_mission(path, limits)
    except MissionError as exc:
        return 2, _one_line(str(exc), max_chars=1000)
    return 0, f"{os.fspath(path)}: valid: {mission.summary()}"
