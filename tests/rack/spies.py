"""Spies for the rack tracker's tests: wrappers that record what the tracker asked."""

from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest


def spy_edges_see_along(monkeypatch: pytest.MonkeyPatch, module: ModuleType) -> list[bool]:
    """Replace `module.edges_see_along` by a wrapper that records each answer; returns the list it appends to."""
    seen: list[bool] = []
    real = module.edges_see_along

    def spy(A: np.ndarray, w: np.ndarray, R: np.ndarray) -> bool:
        seen.append(bool(real(A, w, R)))
        return seen[-1]

    monkeypatch.setattr(module, "edges_see_along", spy)
    return seen
