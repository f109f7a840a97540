"""Pictures people look at before they read numbers: colour-mapped range maps."""
from __future__ import annotations

import numpy as np


def range_picture(range_m: np.ndarray, image: np.ndarray | None = None, *, max_range_m: float | None = None,
                  confidence: np.ndarray | None = None) -> np.ndarray:
    """BGR uint8 picture: inverse range coloured (near = red/yellow, far = blue), unknown = grey image,
    at infinity = black. Shown beside the reference image when ``image`` is given."""
    import cv2
    r = np.asarray(range_m, np.float32)
    finite = np.isfinite(r) & (r > 0)
    if max_range_m is None:
        max_range_m = float(np.percentile(r[finite], 95)) if finite.any() else 1.0
    min_range_m = float(np.percentile(r[finite], 1)) if finite.any() else 0.0
    inv = np.zeros_like(r)
    inv[finite] = 1.0 / r[finite]
    lo, hi = 1.0 / max(max_range_m, 1e-6), 1.0 / max(min_range_m, 1e-6) if min_range_m > 0 else 1.0
    t = np.clip((inv - lo) / max(hi - lo, 1e-12), 0, 1)
    col = cv2.applyColorMap((t * 255).astype(np.uint8), cv2.COLORMAP_TURBO)
    if image is not None:
        g = np.clip(np.asarray(image, np.float32), 0, 255).astype(np.uint8)
        grey = cv2.cvtColor(g, cv2.COLOR_GRAY2BGR) if g.ndim == 2 else g
    else:
        grey = np.full(r.shape + (3,), 96, np.uint8)
    out = np.where(finite[..., None], col, (grey * 0.5).astype(np.uint8))
    out[np.isposinf(r)] = 0
    if confidence is not None:
        c = np.asarray(confidence, np.float32)
        pos = c[finite & (c > 0)]
        if pos.size:
            low = finite & (c < np.percentile(pos, 10))
            out[low] = (out[low] * 0.5).astype(np.uint8)
    if image is not None:
        out = np.concatenate([grey, out], axis=1)
    return out


def write_range_png(path, range_m, image=None, **kw) -> None:
    import cv2
    if not cv2.imwrite(str(path), range_picture(range_m, image, **kw)):
        from . import EonavError
        raise EonavError(f"could not write picture {path}")
