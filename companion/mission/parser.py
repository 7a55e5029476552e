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

import os
from pathlib import Path

from lxml import etree

from companion.errors import MissionError
from companion.mission.model import Action, Frame, Mission, MissionLimits, RackLayout
from companion.mission.parser_actions import _Defaults, _parse_action, _parse_rack
from companion.mission.parser_fields import _Checker, _Element
from companion.mission.parser_xml import MAX_MISSION_BYTES, _check_raw, _parse_xml, _validate_schema
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

DEFAULT_TIMEOUT_S = 60.0
DEFAULT_SPEED_M_S = 0.5
DEFAULT_THRESHOLD_M = 0.2
DEFAULT_YAW_THRESHOLD_DEG = 5.0
DEFAULT_SETTLE_S = 0.5


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
