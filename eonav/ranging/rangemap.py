"""The result of every range estimator: a per-pixel range map on the reference (first) frame's grid."""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

# Per-pixel flag bits (uint8). VALID means range_m holds an estimate the method stands behind (measured); FILLED
# means range_m holds an inferred one (with its own sigma); neither: range_m is NaN.
VALID = 1
TRUNCATION = 2        # eq. (7) truncation-error test failed: first-order Taylor model not trusted here
ILL_CONDITIONED = 4   # near the focus of expansion or gradient perpendicular to the epipolar direction
OUT_OF_VIEW = 8       # the point leaves image b, or is occluded there
LOW_TEXTURE = 16      # too little gradient / irradiance change to measure anything
AT_INFINITY = 32      # inverse range indistinguishable from 0 (sky): range_m = +inf
FILLED = 64           # not measured: range inferred from the measured pixels around (plane fit); not VALID
OCCLUDED = 128        # with OUT_OF_VIEW: in view of image b but hidden there (the residual says so)

FLAG_NAMES = {VALID: "valid", TRUNCATION: "truncation", ILL_CONDITIONED: "ill_conditioned",
              OUT_OF_VIEW: "out_of_view", LOW_TEXTURE: "low_texture", AT_INFINITY: "at_infinity",
              FILLED: "filled", OCCLUDED: "occluded"}


@dataclass
class RangeResult:
    """range_m: float32 H x W, x_c along the optical axis of frame 1; NaN = no estimate, +inf = at infinity.
    confidence: float32 H x W, >= 0, larger is better (0 where no estimate).
    inv_range_per_m / inv_range_std_per_m: float32 H x W or None (rho = 1/x_c and its 1-sigma).
    flags: uint8 H x W bitmask of the constants above, or None."""
    range_m: np.ndarray
    confidence: np.ndarray
    method: str
    inv_range_per_m: np.ndarray | None = None
    inv_range_std_per_m: np.ndarray | None = None
    flags: np.ndarray | None = None
    info: dict = field(default_factory=dict)

    def arrays(self) -> dict:
        """Arrays for an .npz file: range_m and confidence always, the others when present."""
        out = {"range_m": self.range_m.astype(np.float32), "confidence": self.confidence.astype(np.float32)}
        if self.inv_range_per_m is not None:
            out["inv_range_per_m"] = self.inv_range_per_m.astype(np.float32)
        if self.inv_range_std_per_m is not None:
            out["inv_range_std_per_m"] = self.inv_range_std_per_m.astype(np.float32)
        if self.flags is not None:
            out["flags"] = self.flags.astype(np.uint8)
        return out
