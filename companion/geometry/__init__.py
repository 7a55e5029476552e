"""Geometry: SO(3), SE(3) and the project's fixed frames."""

from companion.geometry import frames, se3, so3

__all__ = ["frames", "se3", "so3"]
