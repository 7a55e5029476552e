"""Geometric model of a pipe-rack (Lippiello & Cacace, section III) and its TOML loader.

Frame `rack` (the paper's frame P): parallel pipes lie on the support plane z = 0 with
their axes along +y, numbered left to right (increasing x) looking along +y; x = 0 at
the left surface of pipe 1; z up. Each parallel pipe rests on z = 0 (axis at z = r)
and runs from y = 0 to y = length. Lengths in metres.

The gap parameters are the paper's cumulative gaps d̄_k = d_1 + ... + d_k (eq. 24):
parallel pipe i (1-based, i >= 2) is shifted along +x by d̄_{i-1} from where it would be
if all pipes touched. Extra pipes (e.g. one crossing the others) do not move with gaps.
"""

from __future__ import annotations

import os
import tomllib
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.checks import FloatArray
from companion.errors import InputError, TrackingError

_TOUCH_TOL_M = 1e-6


class RackModelError(TrackingError, InputError):
    """The rack geometry is invalid (non-positive radius, overlapping pipes, bad file)."""


def _vec3(x: Any, name: str) -> tuple[float, float, float]:
    try:
        arr = np.asarray(x, dtype=np.float64).ravel()
    except (TypeError, ValueError) as exc:
        raise RackModelError(f"{name}: expected 3 numbers") from exc
    if arr.size != 3 or not np.all(np.isfinite(arr)):
        raise RackModelError(f"{name}: expected 3 finite numbers, got {x!r}")
    return (float(arr[0]), float(arr[1]), float(arr[2]))


@dataclass(frozen=True)
class Pipe:
    """A straight pipe: axis from `start` (rack frame, m) along unit `direction` for `length` m."""

    radius: float
    start: tuple[float, float, float]
    direction: tuple[float, float, float] = (0.0, 1.0, 0.0)
    length: float = 10.0

    def __post_init__(self) -> None:
        if not np.isfinite(self.radius) or self.radius <= 0.0:
            raise RackModelError(f"radius: must be positive, got {self.radius}")
        if not np.isfinite(self.length) or self.length <= 0.0:
            raise RackModelError(f"length: must be positive, got {self.length}")
        start = _vec3(self.start, "start")
        d = np.asarray(_vec3(self.direction, "direction"))
        n = float(np.linalg.norm(d))
        if n < 1e-9:
            raise RackModelError("direction: must be a non-zero vector")
        d = d / n
        object.__setattr__(self, "radius", float(self.radius))
        object.__setattr__(self, "length", float(self.length))
        object.__setattr__(self, "start", start)
        object.__setattr__(self, "direction", (float(d[0]), float(d[1]), float(d[2])))

    @property
    def start_m(self) -> FloatArray:
        return np.asarray(self.start, dtype=np.float64)

    @property
    def direction_unit(self) -> FloatArray:
        return np.asarray(self.direction, dtype=np.float64)


def _segment_distance(p0: FloatArray, d0: FloatArray, l0: float, p1: FloatArray, d1: FloatArray, l1: float) -> float:
    """Minimum distance between segments p0 + s d0 (s in [0, l0]) and p1 + t d1 (t in [0, l1]); d unit."""
    # Minimise over a fine grid of one parameter with the other solved in closed form, then refine.
    best = np.inf
    s_grid = np.linspace(0.0, l0, 401)
    pts = p0 + s_grid[:, None] * d0
    t = np.clip((pts - p1) @ d1, 0.0, l1)
    dist = np.linalg.norm(pts - (p1 + t[:, None] * d1), axis=1)
    i = int(np.argmin(dist))
    lo, hi = s_grid[max(i - 1, 0)], s_grid[min(i + 1, s_grid.size - 1)]
    for _ in range(60):  # golden-free ternary search on a convex function
        a, b = lo + (hi - lo) / 3.0, hi - (hi - lo) / 3.0
        fa = float(np.linalg.norm(p0 + a * d0 - (p1 + np.clip((p0 + a * d0 - p1) @ d1, 0.0, l1) * d1)))
        fb = float(np.linalg.norm(p0 + b * d0 - (p1 + np.clip((p0 + b * d0 - p1) @ d1, 0.0, l1) * d1)))
        if fa < fb:
            hi = b
        else:
            lo = a
        best = min(best, fa, fb)
    return float(min(best, dist.min()))


@dataclass(frozen=True)
class PipeArrays:
    """All pipes of a model as arrays (M pipes), rack frame, metres.

    `gap_index[m]` is the index k of the cumulative gap d̄_{k+1} (0-based) that shifts pipe m
    along +x, or -1 for pipe 1 and extra pipes.
    """

    starts: FloatArray  # (M, 3)
    directions: FloatArray  # (M, 3) unit
    radii: FloatArray  # (M,)
    lengths: FloatArray  # (M,)
    gap_index: np.ndarray[Any, np.dtype[np.intp]]  # (M,)


@dataclass(frozen=True)
class RackModel:
    """A pipe-rack: parallel pipes (radii, surface-to-surface gaps, common length) plus extra pipes.

    `radii[i]` is the radius of parallel pipe i+1 (m), `gaps[i]` the surface-to-surface distance
    between parallel pipes i+1 and i+2 (the paper's d_{i+1}, m), `length` the common length (m).
    """

    radii: tuple[float, ...]
    gaps: tuple[float, ...]
    length: float = 10.0
    extra: tuple[Pipe, ...] = ()

    def __post_init__(self) -> None:
        radii = tuple(float(r) for r in self.radii)
        gaps = tuple(float(g) for g in self.gaps)
        if len(radii) < 1:
            raise RackModelError("radii: a rack needs at least one parallel pipe")
        if len(gaps) != len(radii) - 1:
            raise RackModelError(f"gaps: expected {len(radii) - 1} gaps for {len(radii)} pipes, got {len(gaps)}")
        for i, r in enumerate(radii):
            if not np.isfinite(r) or r <= 0.0:
                raise RackModelError(f"radii[{i}]: must be positive, got {r}")
        for i, g in enumerate(gaps):
            if not np.isfinite(g):
                raise RackModelError(f"gaps[{i}]: must be finite, got {g}")
            if g < -_TOUCH_TOL_M:
                raise RackModelError(f"gaps[{i}]: pipes {i + 1} and {i + 2} overlap (gap {g} m < 0)")
        if not np.isfinite(self.length) or self.length <= 0.0:
            raise RackModelError(f"length: must be positive, got {self.length}")
        extra = tuple(self.extra)
        for i, p in enumerate(extra):
            if not isinstance(p, Pipe):
                raise RackModelError(f"extra[{i}]: expected a Pipe, got {type(p).__name__}")
        object.__setattr__(self, "radii", radii)
        object.__setattr__(self, "gaps", gaps)
        object.__setattr__(self, "length", float(self.length))
        object.__setattr__(self, "extra", extra)
        self._check_overlaps()

    # ------------------------------------------------------------------ constructors
    @classmethod
    def parallel(
        cls,
        radii: Any,
        gaps: Any,
        length: float = 10.0,
        extra: Any = (),
    ) -> RackModel:
        """Parallel pipes left to right (radii, m), surface gaps to the next pipe (m), extra pipes."""
        return cls(
            radii=tuple(float(r) for r in np.atleast_1d(np.asarray(radii, dtype=np.float64))),
            gaps=tuple(float(g) for g in np.atleast_1d(np.asarray(gaps, dtype=np.float64))) if len(gaps) else (),
            length=float(length),
            extra=tuple(extra),
        )

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> RackModel:
        """Load a rack from a TOML file (format in docs/rack.md); raises RackModelError naming the key."""
        p = Path(path)
        try:
            data = tomllib.loads(p.read_text(encoding="utf-8"))
        except FileNotFoundError as exc:
            raise RackModelError(f"{p}: file not found") from exc
        except tomllib.TOMLDecodeError as exc:
            raise RackModelError(f"{p}: invalid TOML ({exc})") from exc
        return cls.from_dict(data, source=str(p))

    @classmethod
    def from_dict(cls, data: dict[str, Any], source: str = "<dict>") -> RackModel:
        """Build from the TOML structure: length_m, [[pipes]] (radius_m, gap_m), [[extra]]."""
        try:
            length = float(data.get("length_m", 10.0))
            pipes = data["pipes"]
            if not isinstance(pipes, list) or not pipes:
                raise RackModelError(f"{source}: pipes: expected a non-empty array of tables")
            radii: list[float] = []
            gaps: list[float] = []
            for i, tbl in enumerate(pipes):
                if "radius_m" not in tbl:
                    raise RackModelError(f"{source}: pipes[{i}].radius_m: missing")
                radii.append(float(tbl["radius_m"]))
                if i < len(pipes) - 1:
                    if "gap_m" not in tbl:
                        raise RackModelError(f"{source}: pipes[{i}].gap_m: missing (gap to the next pipe)")
                    gaps.append(float(tbl["gap_m"]))
            extra: list[Pipe] = []
            for i, tbl in enumerate(data.get("extra", [])):
                for key in ("radius_m", "start_m", "direction", "length_m"):
                    if key not in tbl:
                        raise RackModelError(f"{source}: extra[{i}].{key}: missing")
                extra.append(
                    Pipe(
                        radius=float(tbl["radius_m"]),
                        start=_vec3(tbl["start_m"], f"extra[{i}].start_m"),
                        direction=_vec3(tbl["direction"], f"extra[{i}].direction"),
                        length=float(tbl["length_m"]),
                    )
                )
        except KeyError as exc:
            raise RackModelError(f"{source}: {exc.args[0]}: missing") from exc
        except (TypeError, ValueError) as exc:
            if isinstance(exc, RackModelError):
                raise RackModelError(f"{source}: {exc}") from exc
            raise RackModelError(f"{source}: {exc}") from exc
        return cls(radii=tuple(radii), gaps=tuple(gaps), length=length, extra=tuple(extra))

    # ------------------------------------------------------------------ derived geometry
    @property
    def num_parallel(self) -> int:
        return len(self.radii)

    @property
    def num_pipes(self) -> int:
        return len(self.radii) + len(self.extra)

    @property
    def cumulative_gaps(self) -> FloatArray:
        """The paper's d̄_1 ... d̄_{n-1} (m), shape (n-1,)."""
        return np.cumsum(np.asarray(self.gaps, dtype=np.float64))

    def with_cumulative_gaps(self, cumulative_gaps: Any) -> RackModel:
        """The same rack with cumulative gaps d̄ (m) replaced."""
        dbar = np.asarray(cumulative_gaps, dtype=np.float64).ravel()
        if dbar.size != self.num_parallel - 1:
            raise RackModelError(f"cumulative_gaps: expected {self.num_parallel - 1} values, got {dbar.size}")
        gaps = np.diff(np.concatenate([[0.0], dbar]))
        return RackModel(radii=self.radii, gaps=tuple(float(g) for g in gaps), length=self.length, extra=self.extra)

    def pipe_arrays(self, cumulative_gaps: Any = None) -> PipeArrays:
        """All pipes (parallel first, left to right, then extra) as arrays, with optional gaps d̄ (m)."""
        dbar = self.cumulative_gaps if cumulative_gaps is None else np.asarray(cumulative_gaps, dtype=np.float64)
        r = np.asarray(self.radii, dtype=np.float64)
        n = r.size
        # Axis x of pipe i when all pipes touch: r_1 + sum_{k<i} 2 r_k + ... = 2*sum(r_<i) + r_i.
        x_touch = 2.0 * np.concatenate([[0.0], np.cumsum(r)[:-1]]) + r
        x = x_touch + np.concatenate([[0.0], dbar])
        starts = np.zeros((n, 3))
        starts[:, 0] = x
        starts[:, 2] = r
        dirs = np.tile([0.0, 1.0, 0.0], (n, 1))
        lengths = np.full(n, self.length)
        gap_index = np.arange(-1, n - 1, dtype=np.intp)
        if self.extra:
            starts = np.vstack([starts, [p.start for p in self.extra]])
            dirs = np.vstack([dirs, [p.direction for p in self.extra]])
            r = np.concatenate([r, [p.radius for p in self.extra]])
            lengths = np.concatenate([lengths, [p.length for p in self.extra]])
            gap_index = np.concatenate([gap_index, np.full(len(self.extra), -1, dtype=np.intp)])
        return PipeArrays(starts=starts, directions=dirs, radii=r, lengths=lengths, gap_index=gap_index)

    def pipes(self, cumulative_gaps: Any = None) -> list[Pipe]:
        """All pipes as `Pipe` objects (parallel first, then extra)."""
        a = self.pipe_arrays(cumulative_gaps)
        return [
            Pipe(radius=float(a.radii[i]), start=_vec3(a.starts[i], "start"), direction=_vec3(a.directions[i], "d"),
                 length=float(a.lengths[i]))
            for i in range(a.radii.size)
        ]

    def _check_overlaps(self) -> None:
        a = self.pipe_arrays()
        n = self.num_parallel
        for i in range(n, a.radii.size):
            for j in range(a.radii.size):
                if j >= i:
                    continue
                d = _segment_distance(a.starts[i], a.directions[i], float(a.lengths[i]),
                                      a.starts[j], a.directions[j], float(a.lengths[j]))
                if d < a.radii[i] + a.radii[j] - 1e-4:
                    raise RackModelError(
                        f"extra[{i - n}]: overlaps pipe {j + 1} (axis distance {d:.4f} m < "
                        f"{a.radii[i] + a.radii[j]:.4f} m)"
                    )
