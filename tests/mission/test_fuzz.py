"""Fuzz: 1,000 seeded mutations of valid missions give a complete Mission or a one-line MissionError."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from lxml import etree

from companion.mission import Mission, MissionError, parse_mission
from companion.mission.model import GotoXY, GotoZ, Home, Hover, Land, Servo, Takeoff, TakePhoto

REPO = Path(__file__).resolve().parents[2]
ALL_ACTIONS = b"""<?xml version="1.0" encoding="UTF-8"?>
<mission version="1" name="all" frame="rack" timeout="30" speed="0.5" settle="0.2">
  <rack length="10"><pipe radius="0.15" gap="0.1"/><pipe radius="0.2" gap="0.1"/><pipe radius="0.15"/></rack>
  <takeoff id="to" height="1.5" threshold="0.1"/>
  <gotoxy x="2.5" y="1" yaw="90" speed="0.4" threshold="0.05" yaw-threshold="3" timeout="40"/>
  <gotoz z="2.0" speed="0.3" threshold="0.1"/>
  <gotoz height="3.0"/>
  <take-photo camera="down" id="p1"/>
  <hover seconds="4.5"/>
  <servo pipe="2" height="1.5" y="4" yaw="-45" speed="0.2" threshold="0.1" yaw-threshold="2"/>
  <home speed="0.6" threshold="0.3"/>
  <land timeout="90"/>
</mission>
"""
VALUES = [b"", b"-1", b"0", b"1e9", b"abc", b"NaN", b"INF", b"9" * 400, b"0.0001", b"12", b"1.5", b"-0",
          b"&amp;", b"&lt;", b"&x;", b"\xc3\xa9", b"\xff", b"99999999999999999999", b"3.", b".5", b"+2", b" 1 ",
          b"ned", b"rack", b"enu", b"1 2", b"'", b'"', b"<", b">", b"]]>", b"7"]
ACTION_TYPES = (Takeoff, GotoXY, GotoZ, TakePhoto, Hover, Servo, Home, Land)
ATTRIBUTE = re.compile(rb'="([^"]*)"')


def mutate(data: bytes, rng: np.random.Generator) -> bytes:
    buf = bytearray(data)
    for _ in range(int(rng.integers(1, 4))):
        kind = int(rng.integers(0, 6))
        if kind == 0 and buf:  # byte flips
            for _ in range(int(rng.integers(1, 4))):
                i = int(rng.integers(0, len(buf)))
                buf[i] ^= 1 << int(rng.integers(0, 8))
        elif kind == 1 and buf:  # delete a span
            i = int(rng.integers(0, len(buf)))
            del buf[i:i + int(rng.integers(1, 20))]
        elif kind in (2, 3):  # duplicate or delete a line
            lines = bytes(buf).split(b"\n")
            j = int(rng.integers(0, len(lines)))
            if kind == 2:
                lines.insert(j, lines[j])
            else:
                del lines[j]
            buf = bytearray(b"\n".join(lines))
        else:  # replace one attribute value
            spans = [m.span(1) for m in ATTRIBUTE.finditer(bytes(buf))]
            if spans:
                a, b = spans[int(rng.integers(0, len(spans)))]
                buf[a:b] = VALUES[int(rng.integers(0, len(VALUES)))]
    return bytes(buf)


def count_actions(data: bytes) -> int:
    parser = etree.XMLParser(resolve_entities=False, no_network=True, load_dtd=False, remove_comments=True)
    root = etree.fromstring(data, parser)
    return sum(1 for child in root if isinstance(child.tag, str) and child.tag != "rack")


def test_thousand_mutated_missions_fail_cleanly_or_parse_completely() -> None:
    rng = np.random.default_rng(6)
    seeds = [ALL_ACTIONS] + [p.read_bytes() for p in sorted((REPO / "missions" / "examples").glob("*.xml"))]
    valid = errors = 0
    for k in range(1000):
        data = mutate(seeds[k % len(seeds)], rng)
        try:
            mission = parse_mission(data, "fuzz.xml")
        except MissionError as exc:
            message = str(exc)
            assert message.startswith("fuzz.xml"), message
            assert "\n" not in message and len(message) < 600, message
            assert re.match(r"fuzz\.xml(:\d+)?: [\w.\-?]+", message), message
            errors += 1
            continue
        assert isinstance(mission, Mission)
        assert len(mission.actions) == count_actions(data) > 0
        assert all(isinstance(a, ACTION_TYPES) for a in mission.actions)
        valid += 1
    assert valid + errors == 1000
    assert valid > 20 and errors > 500  # both outcomes are exercised
