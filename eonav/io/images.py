"""Image loading: colour or grey, 8 or 16 bit, to float32 grey on the 8-bit scale (0..255)."""
from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

from eonav import InputError


def to_grey_f32(img: np.ndarray) -> np.ndarray:
    """Any 2-D grey or 3/4-channel BGR(A) image, uint8/uint16/float, to float32 grey on the 0..255 scale."""
    a = np.asarray(img)
    if a.ndim == 3 and a.shape[2] == 1:
        a = a[:, :, 0]
    if a.ndim == 3 and a.shape[2] in (3, 4):
        scale = 1.0 / 257.0 if a.dtype == np.uint16 else 1.0
        code = cv2.COLOR_BGR2GRAY if a.shape[2] == 3 else cv2.COLOR_BGRA2GRAY
        a = cv2.cvtColor(a.astype(np.float32), code) * np.float32(scale)
        return a
    if a.ndim != 2:
        raise InputError(f"image must be grey (H x W) or colour (H x W x 3/4), got shape {a.shape}")
    if a.dtype == np.uint16:
        return a.astype(np.float32) * np.float32(1.0 / 257.0)
    return a.astype(np.float32)


def load_grey(path) -> np.ndarray:
    """Read an image file (PNG/JPEG/TIFF..., 8 or 16 bit, grey or colour) as float32 grey 0..255."""
    p = Path(path)
    if not p.is_file():
        raise InputError(f"image file not found: {p}")
    img = cv2.imread(str(p), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise InputError(f"cannot decode image {p} (corrupt or unsupported format)")
    return to_grey_f32(img)
