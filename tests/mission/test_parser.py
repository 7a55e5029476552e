"""Mission parser: every action, every validation error, hostile XML, size limits, the CLI helper."""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path

import numpy as np
import pytest

from companion.errors import CompanionError
from companion.mission import (
    MAX_MISSION_BYTES,
    Frame,
    GotoXY,
    GotoZ,
    Home,
    Hover,
    Land,
    MissionError,
    MissionLimits,
    Servo,
    Takeoff,
    TakePhoto,
    load_mission,
    parse_mission,
    validate_cli,
)
from companion.mission.schema import MISSION_XSD

REPO = Path(__file__).resolve().parents[2]
EXAMPLES = REPO / "missions" / "examples"


def doc(body: str, header: str = 'name="t" frame="ned"', rack: str = "") -> str:
    """A mission whose first action is on line 3 (line 1: declaration, line 2: <mission>)."""
    return f'<?xml version="1.0" encoding="UTF-8"?>\n<mission {header}>{rack}\n{body}\n</mission>\n'


def error_of(text: str | bytes, limits: MissionLimits | None = None) -> str:
    with pytest.raises(MissionError) as info:
        parse_mission(text, "m.xml", limits)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith("m.xml")
    return message


def test_schema_file_matches_embedded_copy() -> None:
    assert (REPO / "missions" / "mission.xsd").read_text(encoding="utf-8") == MISSION_XSD


def test_mission_error_is_a_companion_error() -> None:
    assert issubclass(MissionError, CompanionError)


@pytest.mark.parametrize("path", sorted(EXAMPLES.glob("*.xml")), ids=lambda p: p.name)
def test_examples_are_valid(path: Path) -> None:
    mission = load_mission(path)
    assert len(mission.actions) > 0
    code, message = validate_cli(path)
    assert code == 0 and "valid" in message and "\n" not in message


def test_fig6_example_matches_the_paper() -> None:
    m = load_mission(EXAMPLES / "fig6.xml")
    tags = [a.tag for a in m.actions]
    assert tags == ["takeoff", "hover", "take-photo", "hover", "gotoxy", "hover", "take-photo", "hover", "home",
                    "hover", "land"]
    takeoff = m.actions[0]
    assert isinstance(takeoff, Takeoff) and takeoff.height_m == 1.0
    move = m.actions[4]
    assert isinstance(move, GotoXY) and (move.x_m, move.y_m) == (2.0, 0.0)
    assert all(a.duration_s == 5.0 for a in m.actions if isinstance(a, Hover))
    assert m.frame is Frame.NED and m.timeout_s == 30.0


def test_rack_sweep_example_uses_the_five_pipe_rack() -> None:
    m = load_mission(EXAMPLES / "rack_sweep.xml")
    assert m.frame is Frame.RACK and m.rack is not None and m.rack.count == 5
    assert m.rack.length_m == 10.0
    assert all(0.1 <= r <= 0.2 for r in m.rack.radii_m) and all(0.1 <= g <= 0.3 for g in m.rack.gaps_m)
    servos = [a for a in m.actions if isinstance(a, Servo)]
    assert {s.pipe for s in servos} == {1, 3, 5}
    for s in servos:
        assert 1.5 <= s.height_m <= 3.0
        assert 0.0 <= s.y_m <= 10.0


def test_every_action_with_all_attributes() -> None:
    body = "\n".join([
        '<takeoff id="to" height="1.5" threshold="0.1" timeout="20"/>',
        '<gotoxy x="2.5" y="-1" yaw="90" speed="0.4" threshold="0.05" yaw-threshold="3" timeout="40"/>',
        '<gotoz z="-2.0" speed="0.3" threshold="0.1"/>',
        '<gotoz height="3.0"/>',
        '<take-photo camera="down" id="p1"/>',
        '<hover seconds="4.5"/>',
        '<servo pipe="2" height="1.5" y="4" yaw="-45" speed="0.2" threshold="0.1" yaw-threshold="2"/>',
        '<home speed="0.6" threshold="0.3"/>',
        '<land timeout="90"/>',
    ])
    rack = '<rack length="10"><pipe radius="0.15" gap="0.1"/><pipe radius="0.2"/></rack>'
    m = parse_mission(doc(body, 'name="all" frame="ned" timeout="30" speed="0.5" settle="0.25"', rack), "m.xml")
    a = m.actions
    assert [x.line for x in a] == list(range(3, 12))
    assert isinstance(a[0], Takeoff) and a[0] == Takeoff(line=3, id="to", timeout_s=20.0, height_m=1.5,
                                                         threshold_m=0.1)
    assert isinstance(a[1], GotoXY)
    assert a[1].yaw_rad == pytest.approx(math.pi / 2) and a[1].yaw_threshold_rad == pytest.approx(math.radians(3))
    assert (a[1].x_m, a[1].y_m, a[1].speed_m_s, a[1].threshold_m, a[1].timeout_s) == (2.5, -1.0, 0.4, 0.05, 40.0)
    assert isinstance(a[2], GotoZ) and a[2].z_m == -2.0 and a[2].height_m is None and a[2].timeout_s == 30.0
    assert isinstance(a[3], GotoZ) and a[3].height_m == 3.0 and a[3].z_m is None and a[3].speed_m_s == 0.5
    assert isinstance(a[4], TakePhoto) and a[4].camera == "down" and a[4].id == "p1"
    assert isinstance(a[5], Hover) and a[5].duration_s == 4.5 and a[5].timeout_s == 4.5 + 30.0
    assert isinstance(a[6], Servo)
    assert (a[6].pipe, a[6].height_m, a[6].y_m) == (2, 1.5, 4.0) and a[6].yaw_rad == pytest.approx(-math.pi / 4)
    assert isinstance(a[7], Home) and a[7].speed_m_s == 0.6 and a[7].threshold_m == 0.3
    assert isinstance(a[8], Land) and a[8].timeout_s == 90.0
    assert a[2].id == "3-gotoz"  # default ids: position-tag
    assert m.settle_s == 0.25 and m.rack is not None and m.rack.pipe_axis_x_m(2) == pytest.approx(0.6)
    with pytest.raises(dataclasses.FrozenInstanceError):
        m.name = "x"  # type: ignore[misc]


def test_defaults_come_from_the_header_and_module() -> None:
    m = parse_mission(doc('<gotoxy x="1" y="2"/>\n<take-photo camera="c"/>'), "m.xml")
    g = m.actions[0]
    assert isinstance(g, GotoXY)
    assert g.timeout_s == 60.0 and g.speed_m_s == 0.5 and g.threshold_m == 0.2 and g.yaw_rad is None
    assert g.yaw_threshold_rad == pytest.approx(math.radians(5.0))
    assert m.settle_s == 0.5 and m.rack is None and m.source_name == "m.xml"


def test_str_bytes_bom_and_comments_accepted() -> None:
    text = doc('<!-- a comment --><hover seconds="1"/>')
    a = parse_mission(text)
    b = parse_mission(text.encode("utf-8"))
    c = parse_mission(b"\xef\xbb\xbf" + text.encode("utf-8"))
    d = parse_mission('<mission name="t" frame="rack"><hover seconds="1"/></mission>')
    assert a.actions == b.actions == c.actions
    assert d.frame is Frame.RACK and a.source_name == "<string>"


LIMIT_CASES = [
    # (body, header, rack, expected line, expected "field: message" regex)
    ('<gotoxy x="1" y="1" speed="2.0"/>', None, "", 3, r"gotoxy\.speed: 2 m/s exceeds the vehicle limit 1 m/s"),
    ('<gotoxy x="1" y="1" speed="0"/>', None, "", 3, r"gotoxy\.speed: 0 m/s must be > 0"),
    ('<home speed="-1"/>', None, "", 3, r"home\.speed: -1 m/s must be > 0"),
    ('<takeoff height="12"/>', None, "", 3, r"takeoff\.height: height 12 m is above the ceiling 10 m"),
    ('<takeoff height="0.1"/>', None, "", 3, r"takeoff\.height: .*below the minimum flight height"),
    ('<gotoz height="11"/>', None, "", 3, r"gotoz\.height: height 11 m is above the ceiling"),
    ('<gotoz z="-11"/>', None, "", 3, r"gotoz\.z: z -11 m \(ned frame, a height of 11 m\) is above the ceiling 10 m"),
    ('<gotoz z="3"/>', None, "", 3, r"gotoz\.z: .*below the minimum flight height"),
    ('<gotoz z="10.5"/>', 'name="t" frame="rack"', "", 3, r"gotoz\.z: .*above the ceiling"),
    ('<gotoz/>', None, "", 3, r"gotoz\.height: give exactly one of 'z' or 'height'"),
    ('<gotoz z="-1" height="1"/>', None, "", 3, r"gotoz\.z: give exactly one"),
    ('<gotoz height="1" speed="3"/>', None, "", 3, r"gotoz\.speed: 3 m/s exceeds"),
    ('<gotoxy x="1" y="1" threshold="0.001"/>', None, "", 3, r"gotoxy\.threshold: 0.001 m is outside"),
    ('<gotoxy x="1" y="1" threshold="6"/>', None, "", 3, r"gotoxy\.threshold: 6 m is outside"),
    ('<gotoxy x="1" y="1" yaw-threshold="120"/>', None, "", 3, r"gotoxy\.yaw-threshold: 120 deg is outside"),
    ('<gotoxy x="1" y="1" yaw="400"/>', None, "", 3, r"gotoxy\.yaw: 400 deg is outside"),
    ('<gotoxy x="150" y="1"/>', None, "", 3, r"gotoxy\.x: 150 m is outside the geofence"),
    ('<gotoxy x="1" y="-101"/>', None, "", 3, r"gotoxy\.y: -101 m is outside the geofence"),
    ('<land timeout="0"/>', None, "", 3, r"land\.timeout: 0 s must be > 0"),
    ('<land timeout="7200"/>', None, "", 3, r"land\.timeout: 7200 s exceeds the limit 3600 s"),
    ('<hover seconds="0"/>', None, "", 3, r"hover\.seconds: 0 s must be in"),
    ('<hover seconds="5" timeout="4"/>', None, "", 3, r"hover\.timeout: 4 s must be longer than the hover"),
    ('<servo pipe="3" height="1.5" y="2"/>', None, '<rack length="10"><pipe radius="0.1"/></rack>', 3,
     r"servo\.pipe: pipe 3 does not exist \(the rack has 1 pipes\)"),
    ('<servo pipe="1" height="1.5" y="12"/>', None, '<rack length="10"><pipe radius="0.1"/></rack>', 3,
     r"servo\.y: 12 m is off the pipes"),
    ('<servo pipe="1" height="9.9" y="2"/>', None, '<rack length="10"><pipe radius="0.2"/></rack>', 3,
     r"servo\.height: goal height 10.3 m \(pipe top 0.4 m \+ 9.9 m\) is above the ceiling"),
    ('<servo pipe="1" height="0.05" y="2"/>', None, "", 3, r"servo\.height: height above the pipe 0.05 m is below"),
    ('<hover seconds="1"/>', 'name="t" frame="ned" speed="1.5"', "", 2, r"mission\.speed: 1.5 m/s exceeds"),
    ('<hover seconds="1"/>', 'name="t" frame="ned" timeout="-3"', "", 2, r"mission\.timeout: -3 s must be > 0"),
    ('<hover seconds="1"/>', 'name="t" frame="ned" settle="99"', "", 2, r"mission\.settle: 99 s must be in"),
    ('<hover seconds="1"/>', 'name="t" frame="ned" threshold="9"', "", 2, r"mission\.threshold: 9 m is outside"),
    ('<hover seconds="1" id="a"/>\n<land id="a"/>', None, "", 4,
     r"land\.id: duplicate id 'a' \(first used on line 3\)"),
    ('<hover seconds="1"/>', None, '<rack length="10"><pipe radius="0.1"/><pipe radius="0.1"/></rack>', 2,
     r"pipe\.gap: required on every pipe but the last"),
    ('<hover seconds="1"/>', None, '<rack length="10"><pipe radius="0.1" gap="0.1"/></rack>', 2,
     r"pipe\.gap: the last pipe has no next pipe"),
    ('<hover seconds="1"/>', None, '<rack length="10"><pipe radius="0"/></rack>', 2, r"pipe\.radius: 0 m must be in"),
    ('<hover seconds="1"/>', None, '<rack length="0"><pipe radius="0.1"/></rack>', 2, r"rack\.length: 0 m must be"),
]


@pytest.mark.parametrize(("body", "header", "rack", "line", "pattern"), LIMIT_CASES)
def test_range_errors_name_line_and_field(body: str, header: str | None, rack: str, line: int, pattern: str) -> None:
    message = error_of(doc(body, header or 'name="t" frame="ned"', rack))
    assert message.startswith(f"m.xml:{line}: "), message
    assert re.search(pattern, message), message


def test_limits_are_configurable() -> None:
    text = doc('<gotoxy x="1" y="1" speed="1.5"/>')
    assert "exceeds the vehicle limit 1.2 m/s" in error_of(text, MissionLimits(max_speed_m_s=1.2))
    assert parse_mission(text, limits=MissionLimits(max_speed_m_s=2.0)).limits.max_speed_m_s == 2.0
    assert "above the ceiling 2 m" in error_of(doc('<takeoff height="3"/>'), MissionLimits(ceiling_m=2.0))
    many = doc("\n".join('<hover seconds="1"/>' for _ in range(6)))
    message = error_of(many, MissionLimits(max_actions=5))
    assert re.search(r"m\.xml:8: hover: too many actions \(6, the limit is 5\)", message)


SCHEMA_CASES = [
    ('<flyto x="1"/>', 3, r"flyto: This element is not expected"),
    ('<gotoxy x="1" y="1" foo="2"/>', 3, r"gotoxy\.foo: The attribute 'foo' is not allowed"),
    ('<gotoxy x="1"/>', 3, r"gotoxy\.y: required attribute is missing"),
    ('<gotoxy x="abc" y="1"/>', 3, r"gotoxy\.x: 'abc' is not a valid value of a plain decimal number"),
    ('<gotoxy x="1e3" y="1"/>', 3, r"gotoxy\.x: '1e3' is not a valid value"),
    ('<gotoxy x="NaN" y="1"/>', 3, r"gotoxy\.x: 'NaN' is not a valid value"),
    ('<take-photo/>', 3, r"take-photo\.camera: required attribute is missing"),
    ('<take-photo camera="a b"/>', 3, r"take-photo\.camera: "),
    ('<servo pipe="0" height="1" y="1"/>', 3, r"servo\.pipe: "),
    ('<servo pipe="1.5" height="1" y="1"/>', 3, r"servo\.pipe: '1.5' is not a valid value of a pipe index"),
    ('<hover seconds="1">text</hover>', 3, r"hover: "),
    ('<land/><rack length="1"><pipe radius="0.1"/></rack>', 3, r"rack: This element is not expected"),
]


@pytest.mark.parametrize(("body", "line", "pattern"), SCHEMA_CASES)
def test_schema_errors_name_line_and_field(body: str, line: int, pattern: str) -> None:
    message = error_of(doc(body))
    assert message.startswith(f"m.xml:{line}: "), message
    assert re.search(pattern, message), message


@pytest.mark.parametrize(
    ("text", "pattern"),
    [
        ('<mission name="t" frame="enu"><land/></mission>', r"m\.xml:1: mission\.frame: .*'enu'"),
        ('<mission frame="ned"><land/></mission>', r"m\.xml:1: mission\.name: required attribute is missing"),
        ('<mission name="t" frame="ned"></mission>', r"m\.xml:1: mission: .*Missing child element"),
        ('<mission name="t" frame="ned" version="2"><land/></mission>', r"m\.xml:1: mission\.version: "),
        ('<plan name="t" frame="ned"><land/></plan>', r"m\.xml:1: plan: No matching global declaration"),
        ('<mission name="t" frame="ned"><land/>', r"m\.xml:1: xml: not well-formed"),
        ('<mission name="t" frame="ned">\n<land/>\n</misson>', r"m\.xml:3: xml: not well-formed"),
        ("", r"m\.xml:1: mission: the file is empty"),
        ("   \n ", r"m\.xml:1: mission: the file is empty"),
    ],
)
def test_document_level_errors(text: str, pattern: str) -> None:
    assert re.search(pattern, error_of(text)), error_of(text)


def test_encoding_errors() -> None:
    bad = doc('<hover seconds="1"/>').encode("utf-8").replace(b"seconds", b"sec\xffnds")
    assert re.search(r"m\.xml:3: encoding: not valid UTF-8 at byte \d+", error_of(bad))
    assert "NUL byte" in error_of(doc('<hover seconds="1"/>').encode() + b"\x00")
    latin = b'<?xml version="1.0" encoding="ISO-8859-1"?>\n<mission name="t" frame="ned"><land/></mission>'
    assert "m.xml:1: encoding: declared encoding 'ISO-8859-1' is not supported" in error_of(latin)
    utf16 = doc('<hover seconds="1"/>').replace("UTF-8", "UTF-16").encode("utf-16")
    assert "encoding" in error_of(utf16)
    with pytest.raises(MissionError, match="expected str or bytes"):
        parse_mission(42)  # type: ignore[arg-type]


BILLION_LAUGHS = """<?xml version="1.0"?>
<!DOCTYPE lolz [
 <!ENTITY lol "lol">
 <!ENTITY lol1 "&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;&lol;">
 <!ENTITY lol2 "&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;&lol1;">
 <!ENTITY lol3 "&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;&lol2;">
 <!ENTITY lol9 "&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;&lol3;">
]>
<mission name="&lol9;" frame="ned"><land/></mission>
"""


def test_billion_laughs_is_refused_before_parsing() -> None:
    message = error_of(BILLION_LAUGHS)
    assert message.startswith("m.xml:2: DOCTYPE: DTD and entity declarations are not allowed")


@pytest.mark.parametrize(
    "url", ["file:///etc/passwd", "http://127.0.0.1:9/evil.dtd", "https://example.invalid/x"]
)
def test_external_entities_are_refused(url: str) -> None:
    text = (f'<?xml version="1.0"?>\n<!DOCTYPE m [<!ENTITY xxe SYSTEM "{url}">]>\n'
            '<mission name="t" frame="ned"><take-photo camera="&xxe;"/></mission>')
    assert "DOCTYPE: DTD and entity declarations are not allowed" in error_of(text)
    external_dtd = (f'<?xml version="1.0"?>\n<!DOCTYPE mission SYSTEM "{url}">\n'
                    '<mission name="t" frame="ned"><land/></mission>')
    assert "m.xml:2: DOCTYPE" in error_of(external_dtd)


def test_entity_without_doctype_and_sneaky_declarations() -> None:
    # An undeclared entity reference is a well-formedness error, never a lookup.
    assert "xml: not well-formed" in error_of(doc('<take-photo camera="&passwd;"/>'))
    assert "ENTITY" in error_of(doc('<!ENTITY x "y"><land/>'))
    assert "DOCTYPE" in error_of(doc("<land/>").replace("<mission", "<!doctype mission>\n<mission", 1))


def test_processing_instructions_are_refused() -> None:
    text = doc("<?php system('id') ?>\n<land/>")
    assert re.search(r"m\.xml:3: processing-instruction: '<\?php' is not allowed", error_of(text))
    stylesheet = '<?xml-stylesheet href="http://x/y.xsl"?>\n' + doc("<land/>")
    assert "processing-instruction" in error_of(stylesheet)
    late_declaration = "\n" + doc("<land/>")
    assert "processing-instruction" in error_of(late_declaration)


def test_one_megabyte_of_garbage(rng: np.random.Generator) -> None:
    garbage = rng.integers(0, 256, size=1_000_000, dtype=np.uint8).tobytes()
    assert error_of(garbage)
    ascii_garbage = rng.integers(32, 127, size=1_000_000, dtype=np.uint8).tobytes()
    assert error_of(ascii_garbage)
    deep = ("<mission name='t' frame='ned'>" + "<a>" * 100_000).encode()
    assert error_of(deep)


def test_size_limit(tmp_path: Path) -> None:
    big = doc("<land/>" + " " * MAX_MISSION_BYTES)
    assert re.search(r"m\.xml: file is \d+ bytes, above the 1048576-byte mission limit", error_of(big))
    path = tmp_path / "big.xml"
    path.write_text(big)
    code, message = validate_cli(path)
    assert code == 2 and "1048576-byte mission limit" in message


def test_load_mission_and_validate_cli(tmp_path: Path) -> None:
    path = tmp_path / "mission.xml"
    path.write_text(doc('<gotoxy x="1" y="1" speed="2.0"/>'))
    with pytest.raises(MissionError, match=r"mission\.xml:3: gotoxy\.speed: 2 m/s exceeds the vehicle limit 1 m/s"):
        load_mission(path)
    code, message = validate_cli(path)
    assert code == 2
    assert message == f"{path}:3: gotoxy.speed: 2 m/s exceeds the vehicle limit 1 m/s"
    code, message = validate_cli(tmp_path / "missing.xml")
    assert code == 2 and "cannot read the mission file" in message
    path.write_text(doc('<land/>'))
    assert validate_cli(str(path)) == (0, f"{path}: valid: mission 't' (ned frame): 1 actions")
