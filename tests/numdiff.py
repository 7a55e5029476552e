"""Central differences for Jacobian tests (numeric twins of the analytic ones)."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np


def central_jacobian(f: Callable[[np.ndarray], np.ndarray], x: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """d f / d x by central differences; f maps (n,) to (m,), result (m, n)."""
    x = np.asarray(x, dtype=np.float64)
    f0 = np.asarray(f(x), dtype=np.float64).ravel()
    J = np.zeros((f0.size, x.size))
    for i in range(x.size):
        dx = np.zeros_like(x)
        dx[i] = eps
        J[:, i] = (np.asarray(f(x + dx)).ravel() - np.asarray(f(x - dx)).ravel()) / (2 * eps)
    return J
