"""Reading mission XML safely: steps 1-4 of `companion.mission.parser` (size, UTF-8, no DTD /
entities / processing instructions, hardened lxml, the XML Schema); each failure is a `MissionError`."""

from __future__ import annotations

import re
import threading
from typing import Any

from lxml import etree

from companion.errors import MissionError
from companion.mission.schema import MISSION_XSD

__all__ = ["MAX_MISSION_BYTES"]

MAX_MISSION_BYTES = 1 << 20  # 1 MiB

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
