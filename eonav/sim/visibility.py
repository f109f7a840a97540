"""Which pixels of a simulated reference frame a two-view method can range at all (ground truth, for scoring).

A non-sky pixel of view a is *measurable* from the pair (a, b) when its true 3-D point projects inside image b,
in front of camera b, and (with b's own truth) is not hidden there behind a nearer surface. Pixels that leave b's
view -- the border of the earlier frame in forward flight, one side of a stereo pair -- carry no information in
a two-view pair, so no method can range them; benchmarks report coverage of these pixels beside coverage of all
non-sky pixels.
"""
from __future__ import annotations

import numpy as np

from eonav.geometry.camera import View, pair_geometry


def measurable_in_b(view_a: View, view_b: View, range_a_m: np.ndarray, range_b_m: np.ndarray | None = None,
                    depth_tol: float = 0.03) -> np.ndarray:
    """Boolean mask over a's grid: finite true range (not sky), true match inside image b and in front of b,
    and -- when ``range_b_m`` (b's true range, same convention) is given -- not occluded in b: b's true range at
    the nearest pixel of the match is at least (1 - depth_tol) x the point's depth in b."""
    rng = np.asarray(range_a_m, np.float64)
    finite = np.isfinite(rng) & (rng > 0)
    rho = np.where(finite, 1.0 / np.where(finite, rng, 1.0), 0.0).astype(np.float32)
    ub, vb, den = pair_geometry(view_a, view_b).map_to_b(rho)
    cb = view_b.camera
    ok = finite & (den > 0) & (ub >= 0) & (ub <= cb.width - 1) & (vb >= 0) & (vb <= cb.height - 1)
    if range_b_m is not None:
        ui = np.clip(np.rint(np.nan_to_num(ub)), 0, cb.width - 1).astype(np.intp)
        vi = np.clip(np.rint(np.nan_to_num(vb)), 0, cb.height - 1).astype(np.intp)
        depth_b = np.where(finite, rng, 0.0) * den            # x_c in b = x_c in a x (A0 + B0 rho)
        ok &= np.asarray(range_b_m)[vi, ui] >= (1.0 - depth_tol) * depth_b
    return ok
