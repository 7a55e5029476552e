"""The IMU task: the link's IMU and downward-rangefinder callbacks feed the navigation filter (loop thread)."""

from __future__ import annotations

import logging
from typing import Any

from companion.daemon.state import DaemonState
from companion.errors import CompanionError

__all__ = ["ImuTask"]


class ImuTask(DaemonState):
    """Link callbacks into the navigation filter."""

    def _on_imu(self, sample: Any) -> None:
        if self.nav_filter is None or self._imu_sample_cls is None:
            return
        self.counters.imu_samples += 1
        try:
            self.nav_filter.add_imu(self._imu_sample_cls(sample.stamp_s, sample.gyro_rad_s, sample.accel_m_s2))
        except CompanionError as exc:
            self._event("imu-rejected", level=logging.DEBUG, error=str(exc))

    def _on_message(self, msg: Any) -> None:
        """Feeds new downward rangefinder readings to the filter; the link has decoded them into its state."""
        if msg.get_type() != "DISTANCE_SENSOR" or self.link is None or self.nav_filter is None:
            return
        state = self.link.state
        stamp = state.rangefinder_stamp_s
        if state.rangefinder_m is None or stamp is None or stamp == self._range_stamp_s:
            return  # another orientation, out of range, or already fed
        self._range_stamp_s = stamp
        try:
            self.nav_filter.add_range(float(state.rangefinder_m), float(stamp))
        except CompanionError as exc:
            self._event("range-rejected", level=logging.DEBUG, error=str(exc))
