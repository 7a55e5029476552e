"""RackModel / Pipe: geometry of the rack frame, TOML loading, clear errors on bad geometry."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from companion.errors import InputError, TrackingError
from companion.vision.rack import Pipe, RackModel
from companion.vision.rack.model import RackModelError

REPO = Path(__file__).resolve().parents[2]


def test_parallel_pipes_follow_the_rack_frame() -> None:
    m = RackModel.parallel(radii=[0.15, 0.2, 0.1], gaps=[0.1, 0.05], length=8.0)
    a = m.pipe_arrays()
    # Pipe 1's left surface at x = 0; axes at z = r; surfaces separated by the gaps.
    np.testing.assert_allclose(a.starts[:, 0], [0.15, 0.3 + 0.1 + 0.2, 0.3 + 0.1 + 0.4 + 0.05 + 0.1])
    np.testing.assert_allclose(a.starts[:, 2], [0.15, 0.2, 0.1])
    np.testing.assert_allclose(a.starts[:, 1], 0.0)
    np.testing.assert_allclose(a.directions, np.tile([0.0, 1.0, 0.0], (3, 1)))
    np.testing.assert_allclose(m.cumulative_gaps, [0.1, 0.15])
    np.testing.assert_array_equal(a.gap_index, [-1, 0, 1])


def test_cumulative_gaps_roundtrip_and_shift_only_their_pipe() -> None:
    m = RackModel.parallel(radii=[0.15, 0.15, 0.15, 0.15], gaps=[0.1, 0.1, 0.1])
    w = m.with_cumulative_gaps([0.15, 0.35, 0.5])
    np.testing.assert_allclose(w.gaps, [0.15, 0.2, 0.15])
    dx = w.pipe_arrays().starts[:, 0] - m.pipe_arrays().starts[:, 0]
    np.testing.assert_allclose(dx, [0.0, 0.05, 0.15, 0.2])


def test_load_paper_rack_file() -> None:
    m = RackModel.load(REPO / "missions" / "racks" / "paper_5pipe.toml")
    assert m.num_parallel == 5 and len(m.extra) == 1
    np.testing.assert_allclose(m.gaps, [0.1] * 4)
    np.testing.assert_allclose(m.extra[0].direction, [1.0, 0.0, 0.0])
    assert m.num_pipes == 6


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"radii": [0.1, -0.2], "gaps": [0.1]}, r"radii\[1\]"),
        ({"radii": [0.1, 0.0], "gaps": [0.1]}, r"radii\[1\]"),
        ({"radii": [0.1, 0.2], "gaps": [-0.05]}, "overlap"),
        ({"radii": [0.1, 0.2], "gaps": [0.1, 0.1]}, "expected 1 gaps"),
        ({"radii": [0.1, 0.2], "gaps": [0.1], "length": 0.0}, "length"),
    ],
)
def test_invalid_geometry_raises(kwargs: dict[str, object], match: str) -> None:
    with pytest.raises(RackModelError, match=match) as info:
        RackModel.parallel(**kwargs)  # type: ignore[arg-type]
    assert isinstance(info.value, TrackingError) and isinstance(info.value, InputError)


def test_overlapping_extra_pipe_raises() -> None:
    with pytest.raises(RackModelError, match="overlaps pipe 1"):
        RackModel.parallel(radii=[0.15, 0.15], gaps=[0.1],
                           extra=[Pipe(radius=0.1, start=(-0.5, 2.0, 0.3), direction=(1, 0, 0), length=2.0)])
    # Resting on top (touching) is fine.
    RackModel.parallel(radii=[0.15, 0.15], gaps=[0.1],
                       extra=[Pipe(radius=0.1, start=(-0.5, 2.0, 0.4), direction=(1, 0, 0), length=2.0)])


def test_pipe_validation() -> None:
    with pytest.raises(RackModelError, match="radius"):
        Pipe(radius=0.0, start=(0, 0, 0))
    with pytest.raises(RackModelError, match="direction"):
        Pipe(radius=0.1, start=(0, 0, 0), direction=(0, 0, 0))
    p = Pipe(radius=0.1, start=(0, 0, 0), direction=(0, 3, 4), length=1.0)
    np.testing.assert_allclose(p.direction, [0, 0.6, 0.8])


def test_bad_toml_files(tmp_path: Path) -> None:
    f = tmp_path / "r.toml"
    f.write_text("length_m = 10.0\n[[pipes]]\nradius_m = 0.1\n[[pipes]]\nradius_m = 0.1\n")
    with pytest.raises(RackModelError, match=r"pipes\[0\].gap_m"):
        RackModel.load(f)
    f.write_text("length_m = [\n")
    with pytest.raises(RackModelError, match="invalid TOML"):
        RackModel.load(f)
    with pytest.raises(RackModelError, match="not found"):
        RackModel.load(tmp_path / "missing.toml")
    f.write_text("[[pipes]]\nradius_m = 0.1\n[[extra]]\nradius_m = 0.1\nstart_m = [0, 1]\ndirection = [1, 0, 0]\n"
                 "length_m = 1.0\n")
    with pytest.raises(RackModelError, match="start_m"):
        RackModel.load(f)
