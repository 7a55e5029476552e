"""Pipe-rack localization: model, visible limbs, edge + texture tracking on SE(3) with IRLS."""

from companion.vision.rack.model import Pipe, RackModel, RackModelError
from companion.vision.rack.tracker import RackEstimate, RackTracker, RackTrackerConfig

__all__ = ["Pipe", "RackEstimate", "RackModel", "RackModelError", "RackTracker", "RackTrackerConfig"]
