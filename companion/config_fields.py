"""How a configuration key is typed and checked: value checks, type coercion, the `_Section` mixin.

The section dataclasses (`companion.config_sections`) attach these checks to their fields;
`build_dataclass` builds another module's dataclass from a pass-through table. Re-exported by
`companion.config`.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from collections.abc import Callable, Mapping
from typing import Any, ClassVar, Literal, TypeVar

from companion.errors import ConfigError

__all__ = ["build_dataclass"]

_Check = Callable[[Any], str | None]


# --------------------------------------------------------------------------- value checks
def _gt(bound: float) -> _Check:
    return lambda v: None if v > bound else f"must be > {bound:g}, got {v:g}"


def _ge(bound: float) -> _Check:
    return lambda v: None if v >= bound else f"must be >= {bound:g}, got {v:g}"


def _between(lo: float, hi: float) -> _Check:
    return lambda v: None if lo <= v <= hi else f"must be in [{lo:g}, {hi:g}], got {v:g}"


def _nonempty(v: Any) -> str | None:
    return None if v else "must not be empty"


def _exposure(v: Any) -> str | None:
    if isinstance(v, str):
        return None if v == "auto" else f'must be "auto" or a number > 0, got "{v}"'
    return None if v > 0 else f'must be "auto" or a number > 0, got {v:g}'


def _finite_items(v: Any) -> str | None:
    if v is None:
        return None
    return None if all(math.isfinite(x) for x in v) else "must be finite numbers"


def _positive_items(v: Any) -> str | None:
    if v is None:
        return None
    return None if all(x > 0 for x in v) else "must all be > 0"


def _url(v: Any) -> str | None:
    schemes = ("serial:", "udpin:", "udpout:", "udp:", "tcp:", "tcpin:", "udpbcast:")
    if any(v.startswith(s) for s in schemes) or v.startswith("/dev/"):
        return None
    return f"must start with one of {', '.join(schemes)} or be a /dev path, got {v!r}"


def _urls(v: Any) -> str | None:
    for item in v:
        err = _url(item)
        if err is not None:
            return err
    return None


def _check(*checks: _Check) -> dict[str, Any]:
    return {"checks": checks}


# --------------------------------------------------------------------------- generic machinery
def _type_name(tp: Any) -> str:
    origin = typing.get_origin(tp)
    if origin is Literal:
        return " | ".join(f'"{a}"' if isinstance(a, str) else str(a) for a in typing.get_args(tp))
    if origin in (types.UnionType, typing.Union):
        return " or ".join(_type_name(a) for a in typing.get_args(tp))
    if origin is tuple:
        args = typing.get_args(tp)
        plural = {float: "numbers", int: "integers", str: "strings", bool: "booleans"}.get(args[0], str(args[0]))
        if len(args) == 2 and args[1] is Ellipsis:
            return f"a list of {plural}"
        return f"a list of {len(args)} {plural}"
    if tp is type(None):
        return "absent"
    if origin is dict:
        return "a table"
    return {bool: "a boolean", int: "an integer", float: "a number", str: "a string"}.get(tp, str(tp))


class _Mismatch(Exception):
    pass


def _coerce(value: Any, tp: Any) -> Any:
    """`value` converted to the annotation `tp`, or `_Mismatch`."""
    origin = typing.get_origin(tp)
    if tp is Any:
        return value
    if origin is Literal:
        if value in typing.get_args(tp) and type(value) in {type(a) for a in typing.get_args(tp)}:
            return value
        raise _Mismatch
    if origin in (types.UnionType, typing.Union):
        for option in typing.get_args(tp):
            if option is type(None):
                if value is None:
                    return None
                continue
            try:
                return _coerce(value, option)
            except _Mismatch:
                continue
        raise _Mismatch
    if origin is tuple:
        if not isinstance(value, list | tuple):
            raise _Mismatch
        args = typing.get_args(tp)
        if len(args) == 2 and args[1] is Ellipsis:
            return tuple(_coerce(v, args[0]) for v in value)
        if len(value) != len(args):
            raise _Mismatch
        return tuple(_coerce(v, a) for v, a in zip(value, args, strict=True))
    if origin is dict:
        if not isinstance(value, Mapping):
            raise _Mismatch
        return dict(value)
    if tp is bool:
        if isinstance(value, bool):
            return value
        raise _Mismatch
    if tp is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        raise _Mismatch
    if tp is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            out = float(value)
            if not math.isfinite(out):
                raise _Mismatch
            return out
        raise _Mismatch
    if tp is str:
        if isinstance(value, str):
            return value
        raise _Mismatch
    raise TypeError(f"unsupported config annotation {tp!r}")  # pragma: no cover - programming error


class _Section:
    """Mixin: type coercion and value checks of a frozen config dataclass."""

    SECTION: ClassVar[str] = ""

    def __post_init__(self) -> None:
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):  # type: ignore[arg-type]
            key = f"{self.SECTION}.{f.name}"
            value = getattr(self, f.name)
            try:
                value = _coerce(value, hints[f.name])
            except _Mismatch:
                raise ConfigError(f"{key}: must be {_type_name(hints[f.name])}, got {value!r}") from None
            for check in f.metadata.get("checks", ()):
                if value is None:
                    continue
                message = check(value)
                if message is not None:
                    raise ConfigError(f"{key}: {message}")
            object.__setattr__(self, f.name, value)
        self._cross_check()

    def _cross_check(self) -> None:
        """Checks spanning several fields (override)."""

    def _fail(self, name: str, message: str) -> ConfigError:
        return ConfigError(f"{self.SECTION}.{name}: {message}")


_T = TypeVar("_T")


def build_dataclass(cls: type[_T], values: Mapping[str, Any], path: str, **extra: Any) -> _T:
    """`cls(**values, **extra)` with unknown keys reported as ``ConfigError("<path>.<key>: unknown key")``.

    For pass-through tables (`vision.rack_tracker`, `vision.ground_odometer`,
    `filter`) whose target dataclass lives in another module. A sub-table whose
    field is itself a dataclass is built recursively (`[filter.imu]`); lists
    become tuples for tuple fields. `extra` supplies arguments that do not come
    from the file. Errors raised by the class's own validation are re-raised as
    `ConfigError` naming `path`.
    """
    if not dataclasses.is_dataclass(cls):
        raise TypeError(f"{cls!r} is not a dataclass")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    try:
        hints = typing.get_type_hints(cls)
    except Exception:  # unresolvable annotations: no nested building
        hints = {}
    kwargs: dict[str, Any] = {}
    for key, value in values.items():
        if key not in fields:
            raise ConfigError(f"{path}.{key}: unknown key (valid: {', '.join(sorted(fields))})")
        hint = hints.get(key)
        if isinstance(value, Mapping) and isinstance(hint, type) and dataclasses.is_dataclass(hint):
            value = build_dataclass(hint, value, f"{path}.{key}")
        elif isinstance(value, list) and typing.get_origin(hint) is tuple:
            value = tuple(value)
        kwargs[key] = value
    kwargs.update(extra)
    try:
        return cls(**kwargs)
    except ConfigError:
        raise
    except (TypeError, ValueError) as exc:
        raise ConfigError(f"{path}: {exc}") from exc
