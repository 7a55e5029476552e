"""Descriptor matching with the distance-ratio test, and the speed gate (paper Sec. 5.4)."""

from __future__ import annotations

from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray
from companion.vision.ground.features import Features

IntArray = np.ndarray[Any, np.dtype[np.intp]]
BoolArray = np.ndarray[Any, np.dtype[np.bool_]]


class Matcher:
    """Brute-force nearest-neighbour matcher (Hamming for binary descriptors, L2 otherwise)."""

    def __init__(self, binary: bool, ratio: float) -> None:
        self._norm = cv2.NORM_HAMMING if binary else cv2.NORM_L2
        self._dtype = cv2.CV_32S if binary else cv2.CV_32F
        self._ratio = float(ratio)

    def match(self, prev: Features, cur: Features) -> tuple[IntArray, IntArray]:
        """Indices (i_prev, i_cur) of matches passing the ratio test (each current feature at most once)."""
        if prev.count < 2 or cur.count < 2:
            empty = np.zeros(0, dtype=np.intp)
            return empty, empty
        # Brute-force two nearest neighbours as arrays (what BFMatcher.knnMatch computes, without
        # building a DMatch object per feature).
        dist, idx = cv2.batchDistance(
            cur.descriptors, prev.descriptors, self._dtype, normType=self._norm, K=2, update=0, crosscheck=False
        )
        dist = dist.astype(np.float64)
        keep = dist[:, 0] < self._ratio * dist[:, 1]
        i_cur = np.flatnonzero(keep).astype(np.intp)
        i_prev = idx[keep, 0].astype(np.intp)
        best = dist[keep, 0]
        # One current feature per previous feature: keep the best distance when several claim it.
        order = np.lexsort((best, i_prev))
        first = np.ones(order.size, dtype=bool)
        first[1:] = i_prev[order][1:] != i_prev[order][:-1]
        sel = order[first]
        return i_prev[sel], i_cur[sel]


def speed_gate(
    q_prev_m: FloatArray,
    q_cur_m: FloatArray,
    predicted_dxy_m: FloatArray,
    predicted_dyaw_rad: float,
    radius_m: float,
    yaw_slack_rad: float,
) -> BoolArray:
    """Matches compatible with the vehicle's speed.

    `q_prev_m`, `q_cur_m` (N, 2): ground points of the matched features in the previous frame's
    yaw-rotated level frame (the `a_i`, `b_i` of the solver), metres. A match is kept when
    a_i - (d + R(dyaw) b_i) is shorter than `radius_m + yaw_slack_rad * |b_i|` where (d, dyaw) is
    the predicted increment.
    """
    c, s = np.cos(predicted_dyaw_rad), np.sin(predicted_dyaw_rad)
    bx, by = q_cur_m[:, 0], q_cur_m[:, 1]
    rx = q_prev_m[:, 0] - (predicted_dxy_m[0] + c * bx - s * by)
    ry = q_prev_m[:, 1] - (predicted_dxy_m[1] + s * bx + c * by)
    limit = radius_m + yaw_slack_rad * np.hypot(bx, by)
    keep: BoolArray = rx * rx + ry * ry <= limit * limit
    return keep
