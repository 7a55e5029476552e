"""`companion sim --set SECTION.KEY=VALUE`: configuration overrides on top of the embedded sim configuration.

An integrator rehearses a configuration change in the simulator before flying it: `--set
vision.rack_verify_start=report`, `--set vision.rack_tracker.ground_points=0`. The dotted name is a path into
the TOML configuration (section, then keys, nested tables allowed); the value is read as a TOML value
(`2`, `0.5`, `true`, `[1, 2]`, `"text"`), and a bare word that is not one (`report`) as a string. The merged
configuration goes through the same checks as a configuration file (`companion.config.parse_config`), so an
unknown key or a wrong type is a `ConfigError` naming it (exit 2), before anything starts.
"""

from __future__ import annotations

import tomllib
from collections.abc import Iterable
from typing import Any

from companion.errors import ConfigError

__all__ = ["merge_overrides", "parse_config_sets"]


def _value(text: str) -> Any:
    """A TOML value, or the text itself when it is not one (a bare word)."""
    try:
        return tomllib.loads(f"v = {text}")["v"]
    except tomllib.TOMLDecodeError:
        if not text or any(c in text for c in "[]{}\"'=\n"):
            raise ConfigError(f"--set: {text!r} is not a TOML value") from None
        return text


def parse_config_sets(specs: Iterable[str]) -> dict[str, Any]:
    """`SECTION.KEY[.KEY...]=VALUE` items -> nested overrides {section: {key: value or {...}}}.

    Raises ConfigError on a malformed item (no '=', no dot, an empty name part, a value that is not TOML)."""
    out: dict[str, Any] = {}
    for spec in specs:
        name, sep, text = spec.partition("=")
        parts = [p.strip() for p in name.split(".")]
        if not sep or len(parts) < 2 or not all(parts):
            raise ConfigError(f"--set: expected SECTION.KEY=VALUE, got {spec!r}")
        node = out
        for p in parts[:-1]:
            child = node.setdefault(p, {})
            if not isinstance(child, dict):
                raise ConfigError(f"--set: {name!r} goes inside {p!r}, which another --set gave a value")
            node = child
        if isinstance(node.get(parts[-1]), dict):
            raise ConfigError(f"--set: {name!r} is a table that another --set goes inside")
        node[parts[-1]] = _value(text.strip())
    return out


def merge_overrides(base: dict[str, Any], extra: dict[str, Any]) -> dict[str, Any]:
    """`base` with `extra` merged in, tables merged key by key (neither argument is modified)."""
    out = dict(base)
    for key, value in extra.items():
        if isinstance(value, dict) and isinstance(out.get(key), dict):
            out[key] = merge_overrides(out[key], value)
        else:
            out[key] = value
    return out
