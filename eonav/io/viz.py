"""Pictures people look at before they read numbers: colour-mapped range maps."""
from __future__ import annotations

import numpy as np


def inverse_range_colours(range_m: np.ndarray, valid: np.ndarray, near_m: float, far_m: float) -> np.ndarray:
    """BGR uint8: inverse range on the TURBO colour map, ``near_m`` and nearer = red, ``far_m`` and farther =
    blue; pixels not ``valid`` are black. Inverse range spreads colour where ranges matter (near)."""
    import cv2
    r = np.asarray(range_m, np.float32)
    lo, hi = 1.0 / max(far_m, 1e-6), 1.0 / max(near_m, 1e-6)
    with np.errstate(divide="ignore", invalid="ignore"):
        t = np.clip((1.0 / r - lo) / max(hi - lo, 1e-12), 0.0, 1.0)
    img = cv2.applyColorMap(np.where(valid, t * 255, 0).astype(np.uint8), cv2.COLORMAP_TURBO)
    img[~valid] = 0
    return img


def range_picture(range_m: np.ndarray, image: np.ndarray | None = None, *, max_range_m: float | None = None,
                  confidence: np.ndarray | None = None) -> np.ndarray:
    """The reference image (when given) beside its range map: near = red, far = blue, no estimate or at
    infinity = black; the least confident tenth of the estimates is dimmed. The colour scale runs from the
    1st to the 95th percentile of the estimates unless ``max_range_m`` is given."""
    import cv2
    r = np.asarray(range_m, np.float32)
    finite = np.isfinite(r) & (r > 0)
    far = max_range_m or (float(np.percentile(r[finite], 95)) if finite.any() else 1.0)
    near = float(np.percentile(r[finite], 1)) if finite.any() else far / 10
    out = inverse_range_colours(r, finite, near, far)
    if confidence is not None:
        c = np.asarray(confidence, np.float32)
        pos = c[finite & (c > 0)]
        if pos.size:
            low = finite & (c < np.percentile(pos, 10))
            out[low] = (out[low] * 0.5).astype(np.uint8)
    if image is None:
        return out
    g = np.clip(np.asarray(image, np.float32), 0, 255).astype(np.uint8)
    grey = cv2.cvtColor(g, cv2.COLOR_GRAY2BGR) if g.ndim == 2 else g
    return np.concatenate([grey, out], axis=1)


def write_range_png(path, range_m, image=None, **kw) -> None:
    import cv2
    if not cv2.imwrite(str(path), range_picture(range_m, image, **kw)):
        from eonav import EonavError
        raise EonavError(f"could not write picture {path}")
