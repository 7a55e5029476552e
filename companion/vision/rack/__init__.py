"""Pipe-rack localization: model, visible limbs, edge + texture tracking on SE(3) with IRLS, acquisition."""

from companion.vision.rack.acquire import (
    AcquisitionConfig,
    AcquisitionPrior,
    AcquisitionResult,
    RackHypothesis,
    acquire_rack,
)
from companion.vision.rack.model import Pipe, RackModel, RackModelError
from companion.vision.rack.tracker import RackEstimate, RackTracker, RackTrackerConfig

__all__ = [
    "AcquisitionConfig",
    "AcquisitionPrior",
    "AcquisitionResult",
    "Pipe",
    "RackEstimate",
    "RackHypothesis",
    "RackModel",
    "RackModelError",
    "RackTracker",
    "RackTrackerConfig",
    "acquire_rack",
]
