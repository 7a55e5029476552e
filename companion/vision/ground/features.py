"""Feature detector/descriptor factory (OpenCV) and one detect-and-describe call per frame."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import cv2
import numpy as np

from companion.checks import FloatArray
from companion.errors import ConfigError
from companion.vision.ground.config import GroundOdometerConfig

# The OpenCV stubs do not list every factory; go through an untyped alias.
_cv: Any = cv2


@dataclass(frozen=True)
class Features:
    """Keypoints of one frame: pixel positions (N, 2) float64 and descriptors (N, D)."""

    uv_px: FloatArray
    descriptors: np.ndarray[Any, Any]
    binary: bool

    @property
    def count(self) -> int:
        return int(self.uv_px.shape[0])


class FeatureExtractor:
    """Detects and describes features with the combination named in the config.

    orb       ORB (oriented FAST + rotated BRIEF), Harris-ranked, `pyramid_levels` levels.
    fast-orb  ORB with FAST-score ranking (cheaper), same descriptor.
    gftt-orb  Shi-Tomasi corners (GFTT) described with ORB.
    sift      SIFT detector and descriptor (float, L2).
    akaze     AKAZE (binary MLDB descriptor).
    brisk     BRISK (binary).
    """

    def __init__(self, config: GroundOdometerConfig) -> None:
        self._config = config
        n = config.max_features
        name = config.detector
        self._detector: Any = None
        self._describer: Any
        if name in ("orb", "fast-orb"):
            score = cv2.ORB_HARRIS_SCORE if name == "orb" else cv2.ORB_FAST_SCORE
            self._describer = _cv.ORB_create(
                nfeatures=n,
                scaleFactor=config.pyramid_scale,
                nlevels=config.pyramid_levels,
                edgeThreshold=19,
                patchSize=19,
                scoreType=score,
                fastThreshold=config.fast_threshold,
            )
        elif name == "gftt-orb":
            self._detector = _cv.GFTTDetector_create(maxCorners=n, qualityLevel=0.01, minDistance=7, blockSize=5)
            self._describer = _cv.ORB_create(nfeatures=n, nlevels=1, edgeThreshold=19, patchSize=19)
        elif name == "sift":
            self._describer = _cv.SIFT_create(nfeatures=n)
        elif name == "akaze":
            self._describer = _cv.AKAZE_create(threshold=3e-4)
        elif name == "brisk":
            self._describer = _cv.BRISK_create(thresh=30, octaves=2)
        else:  # pragma: no cover - the config validates names
            raise ConfigError(f"detector: unknown {name!r}")
        self.binary = name != "sift"
        self._adaptive = name in ("orb", "fast-orb")
        self._threshold = float(config.fast_threshold)

    def reset(self) -> None:
        """Back to the configured FAST threshold."""
        self._threshold = float(self._config.fast_threshold)
        if self._adaptive:
            self._describer.setFastThreshold(int(self._threshold))

    def _adapt(self, count: int) -> None:
        """Lower the FAST threshold when a frame is short of features, raise it back otherwise."""
        cfg = self._config
        if count < cfg.max_features:
            new = max(float(cfg.fast_threshold_min), self._threshold * 0.75)
        else:
            new = min(float(cfg.fast_threshold), self._threshold * 1.1 + 0.5)
        if int(new) != int(self._threshold):
            self._describer.setFastThreshold(int(new))
        self._threshold = new

    def extract(self, gray: np.ndarray[Any, Any]) -> Features:
        """Features of a (H, W) uint8 image; at most `max_features`, strongest first."""
        if self._detector is not None or self._config.detector in ("akaze", "brisk"):
            # Detect, keep the strongest, then describe only those (AKAZE and BRISK have no cap).
            detector = self._detector if self._detector is not None else self._describer
            kps = detector.detect(gray, None)
            if len(kps) > self._config.max_features:
                order = np.argsort([-k.response for k in kps], kind="stable")[: self._config.max_features]
                kps = [kps[i] for i in order]
            kps, desc = self._describer.compute(gray, kps)
        else:
            kps, desc = self._describer.detectAndCompute(gray, None)
            if self._adaptive:
                self._adapt(len(kps))
        n_max = self._config.max_features
        if len(kps) > n_max:
            order = np.argsort([-k.response for k in kps], kind="stable")[:n_max]
            kps = [kps[i] for i in order]
            desc = desc[order]
        if desc is None or len(kps) == 0:
            dtype = np.uint8 if self.binary else np.float32
            return Features(np.zeros((0, 2)), np.zeros((0, 32), dtype=dtype), self.binary)
        uv = _cv.KeyPoint_convert(kps).astype(np.float64).reshape(-1, 2)
        return Features(uv, desc, self.binary)
