"""Delayed-state (stochastic cloning) error-state EKF fusing the IMU with the visual estimates.

Tardif et al., section III-B: the IMU predicts at its own rate, visual
measurements correct at camera rate; relative poses from the ground odometer
are applied between a cloned copy of the pose (taken at the previous ground
frame) and the current pose; a failed frame makes no correction and re-clones.
Absolute poses from the rack tracker and rangefinder heights are ordinary
EKF updates. See docs/estimation.md for the models, defaults and the source
selection rules.

Time alignment: the filter keeps ~`buffer_s` of IMU samples, a snapshot of the
filter after each one, and the measurements applied in that window. A
measurement older than the current filter time rolls the filter back to the
last snapshot before its stamp and replays samples and measurements in stamp
order. A measurement newer than the last IMU sample is applied by holding the
last IMU reading; the next IMU sample replays it with the interpolated reading.
"""

from __future__ import annotations

# One module per concern, each a mixin of `FilterState` (filter_state): filter_correction (Kalman update,
# resets), filter_sources (source selection, per-source updates), filter_timeline (initialization, IMU
# prediction, history buffer, replay), filter_inputs (the add_* entry points), filter_outputs (read-outs).
from companion.estimation.filter_inputs import FilterInputs
from companion.estimation.filter_outputs import FilterOutputs

__all__ = ["NavigationFilter"]


class NavigationFilter(FilterInputs, FilterOutputs):
    """IMU-driven error-state EKF with a cloned pose, source selection and measurement rollback.

    Frames: NED world, body FRD. All stamps (s) on one time base (the daemon
    converts autopilot IMU stamps with the TIMESYNC offset). Not thread-safe:
    call it from one thread or task.
    """
