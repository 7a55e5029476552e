"""Navigation filter: delayed-state EKF fusing the autopilot's IMU with the visual estimates.

See docs/estimation.md. Public names:

    NavigationFilter, NavFilterConfig, ImuNoiseModel, ImuSample, NavEstimate,
    NavFilterStats, RackEstimateLike, GroundEstimateLike
"""

from companion.estimation.filter import NavigationFilter
from companion.estimation.types import (
    GroundEstimateLike,
    ImuNoiseModel,
    ImuSample,
    NavEstimate,
    NavFilterConfig,
    NavFilterStats,
    RackEstimateLike,
)

__all__ = [
    "GroundEstimateLike",
    "ImuNoiseModel",
    "ImuSample",
    "NavEstimate",
    "NavFilterConfig",
    "NavFilterStats",
    "NavigationFilter",
    "RackEstimateLike",
]
