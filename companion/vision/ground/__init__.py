"""Downward ground visual odometer (Ortiz et al., Sec. 5): x, y, yaw in NED from a ground camera.

odo = GroundOdometer(cam, GroundOdometerConfig(detector="orb", solver="gen", refine=True, kalman=True))
est = odo.update(image, stamp_s, height_m, roll_rad, pitch_rad)
"""

from companion.vision.ground.baseline import PlanarBaseline, PlanarBaselineEstimate
from companion.vision.ground.config import GroundOdometerConfig
from companion.vision.ground.odometer import GroundEstimate, GroundOdometer

__all__ = [
    "GroundEstimate",
    "GroundOdometer",
    "GroundOdometerConfig",
    "PlanarBaseline",
    "PlanarBaselineEstimate",
]
