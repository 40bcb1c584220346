"""Configuration of the vision measurement pipeline (no OpenCV: configs load on any install)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from .dictionaries import check_marker

__all__ = ["PNP_METHOD_NAMES", "PnpMethod", "CORNER_REFINEMENTS", "CornerRefinement", "DetectorConfig", "PipelineConfig"]

PnpMethod = Literal["ippe_square", "p3p", "sqpnp", "iterative"]
#: OpenCV's ArUco corner refinements (``cv2.aruco.CORNER_REFINE_*``)
CornerRefinement = Literal["none", "subpix", "contour", "apriltag"]
CORNER_REFINEMENTS = ("none", "subpix", "contour", "apriltag")

#: the PnP methods of :mod:`.pnp`
PNP_METHOD_NAMES = ("ippe_square", "p3p", "sqpnp", "iterative")


@dataclass(frozen=True)
class DetectorConfig:
    """The detector: dictionary, corner refinement and its window [px]."""

    dictionary: str = "DICT_4X4_50"
    corner_refinement: CornerRefinement = "subpix"
    refinement_window_px: int = 5

    def __post_init__(self) -> None:
        check_marker(self.dictionary)
        if self.refinement_window_px < 1:
            raise ValueError(f"refinement_window_px must be >= 1, got {self.refinement_window_px}")


@dataclass(frozen=True)
class PipelineConfig:
    """The measurement pipeline: detector, marker length [m] (the black square's side; per id in
    ``marker_lengths_m``, keys the ids as strings), PnP method, ambiguity threshold, the
    covariance's pixel-noise floor [px], LM refinement, and the ids to keep (empty: all).

    The calibration's stated accuracy, which the pose covariance adds to the corners' noise
    (:func:`~.pnp.pose_covariance`): the focal lengths' relative standard deviation
    ``calib_focal_std_frac``, the principal point's ``calib_principal_std_px`` per axis and each
    distortion coefficient's relative ``calib_dist_std_frac`` (all 0: the calibration is exact)."""

    detector: DetectorConfig = field(default_factory=DetectorConfig)
    marker_length_m: float = 0.2
    marker_lengths_m: dict[str, float] = field(default_factory=dict)
    method: PnpMethod = "ippe_square"
    ambiguity_ratio: float = 3.0
    sigma_floor_px: float = 0.3
    refine: bool = False
    ids: tuple[int, ...] = ()
    calib_focal_std_frac: float = 0.0
    calib_principal_std_px: float = 0.0
    calib_dist_std_frac: float = 0.0

    def __post_init__(self) -> None:
        if not self.marker_length_m > 0:
            raise ValueError(f"marker_length_m must be positive, got {self.marker_length_m}")
        for k, v in self.marker_lengths_m.items():
            if not k.isdigit() or not v > 0:
                raise ValueError(f"marker_lengths_m: keys are marker ids, values positive lengths, got {k!r} = {v}")
        if self.method not in PNP_METHOD_NAMES:
            raise ValueError(f"method: one of {', '.join(PNP_METHOD_NAMES)}, got {self.method!r}")
        if not self.ambiguity_ratio >= 1.0:
            raise ValueError(f"ambiguity_ratio must be >= 1, got {self.ambiguity_ratio}")
        if not self.sigma_floor_px > 0:
            raise ValueError(f"sigma_floor_px must be positive, got {self.sigma_floor_px}")
        for name in ("calib_focal_std_frac", "calib_principal_std_px", "calib_dist_std_frac"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0):
                raise ValueError(f"{name} must be >= 0 and finite, got {v}")

    @property
    def calibration_std(self) -> tuple[float, float, float]:
        """``(focal fraction, principal point px, distortion fraction)``."""
        return (self.calib_focal_std_frac, self.calib_principal_std_px, self.calib_dist_std_frac)

    def length_m(self, marker_id: int) -> float:
        return self.marker_lengths_m.get(str(marker_id), self.marker_length_m)
