"""The per-pixel inverse-range state of one camera, on the grid of its newest frame.

Each cell holds the filter's belief about the scene point seen at that pixel:
- ``rho`` (1/m) and ``var`` (1/m^2): Gaussian estimate of the inverse range rho = 1/x_c and its variance (NaN rho:
  an empty cell, nothing known);
- ``a``, ``b``: parameters of the Beta distribution of the cell's inlier ratio (Vogiatzis & Hernandez 2011): the
  evidence that measurements agree with the estimate (a) or do not (b); E[inlier ratio] = a / (a + b);
- ``n``: number of measurements fused into the cell since it (re)started;
- ``du``, ``dv``: where in the pixel the held point projects (offset from the pixel centre, pixels): the forward
  warp rounds each point to a pixel, and keeping the remainder stops slow image motion (a tenth of a pixel a frame)
  from being rounded away frame after frame;
- ``flags``: the last measurement's flag bits (``eonav.ranging.rangemap``) of the cell: why it was not measured, if it was
  not.
``rho_far`` is the state's far limit (1/m): the smallest far inverse range of the pairs fused (AT_INFINITY needs
2 sigma below it, as in a single pair).
"""
from __future__ import annotations

import importlib
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from eonav.geometry.camera import Camera, VehicleState

F32 = np.float32


@dataclass
class InverseRangeState:
    camera: Camera
    pose: VehicleState
    stamp_s: float
    rho: np.ndarray
    var: np.ndarray
    a: np.ndarray
    b: np.ndarray
    n: np.ndarray
    du: np.ndarray
    dv: np.ndarray
    flags: np.ndarray
    rho_far: float = 0.0

    @classmethod
    def empty(cls, camera: Camera, pose: VehicleState, stamp_s: float) -> "InverseRangeState":
        """A state with every cell empty on ``camera``'s grid at ``pose``."""
        shape = (camera.height, camera.width)
        return cls(camera, pose, float(stamp_s), np.full(shape, np.nan, F32), np.full(shape, np.inf, F32),
                   np.zeros(shape, F32), np.zeros(shape, F32), np.zeros(shape, np.uint16),
                   np.zeros(shape, F32), np.zeros(shape, F32), np.zeros(shape, np.uint8), 0.0)

    def clear(self, mask: np.ndarray | None = None) -> None:
        """Cells empty, in place (rho NaN, variance inf, no evidence): every cell, the last measurement's flags too;
        or the cells of ``mask``, whose flags stay those of the last measurement that saw them."""
        sel = Ellipsis if mask is None else np.asarray(mask, bool)
        self.rho[sel] = np.nan
        self.var[sel] = np.inf
        for x in (self.a, self.b, self.n, self.du, self.dv) + ((self.flags,) if mask is None else ()):
            x[sel] = 0

    @property
    def shape(self):
        return self.rho.shape

    def occupied(self) -> np.ndarray:
        """Cells holding an estimate."""
        return np.isfinite(self.rho)


@lru_cache(maxsize=None)
def optional_kernels():
    """The numba passes of predict and update (``eonav.fusion._kernels``), or None without numba (the numpy paths
    run)."""
    try:
        return importlib.import_module(f"{__package__}._kernels")
    except ImportError:
        return None
