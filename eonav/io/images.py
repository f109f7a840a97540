"""Image loading: colour or grey, 8 or 16 bit, to float32 grey on the 8-bit scale (0..255).

The size an image file declares is read from its header (PNG IHDR, JPEG SOF, TIFF first IFD) and checked against
the expected size and a pixel budget BEFORE decoding: a small compressed file can declare a picture of gigabytes,
and the decoder would allocate it all before any check after it. Other formats OpenCV reads are bounded by their
file size (a raw image of the expected size) and checked after decoding.
"""
from __future__ import annotations

import struct
from pathlib import Path

import cv2
import numpy as np

from eonav import InputError
from eonav.io.files import read_regular_file

MAX_IMAGE_PIXELS = 1 << 26          # 8192 x 8192: decoded 16-bit RGBA 512 MiB, float32 grey 256 MiB
RAW_BYTES_PER_PIXEL = 8             # 16-bit RGBA: the largest raw pixel OpenCV decodes from these formats
FILE_SLACK_BYTES = 1 << 20          # headers, metadata, incompressible data on top of the raw pixels


class ImageSizeError(InputError):
    """An image whose size is not the expected one (``size`` = (width, height), from its header or decoded)."""

    def __init__(self, msg: str, size: tuple):
        super().__init__(msg)
        self.size = size


def _png_size(b: bytes):
    if len(b) < 24 or b[12:16] != b"IHDR":
        raise InputError("PNG without an IHDR header")
    return struct.unpack(">II", b[16:24])


def _jpeg_size(b: bytes):
    i = 2
    while i + 4 <= len(b):
        if b[i] != 0xFF:
            raise InputError(f"JPEG segment without a marker at byte {i}")
        m = b[i + 1]
        if m == 0xFF:                       # fill byte
            i += 1
            continue
        if m == 0x01 or 0xD0 <= m <= 0xD8:  # markers without a length
            i += 2
            continue
        if m in (0xD9, 0xDA):               # end of image / start of scan before any frame header
            break
        seg_len = struct.unpack(">H", b[i + 2:i + 4])[0]
        if seg_len < 2:
            raise InputError(f"JPEG segment of length {seg_len} at byte {i}")
        if 0xC0 <= m <= 0xCF and m not in (0xC4, 0xC8, 0xCC):     # SOFn: P, Y (height), X (width), Nf
            if i + 9 > len(b):
                break
            h, w = struct.unpack(">HH", b[i + 5:i + 9])
            if h == 0:                      # height defined later by a DNL marker: not from the header
                return None
            return w, h
        i += 2 + seg_len
    raise InputError("JPEG without a frame header (SOF)")


def _tiff_size(b: bytes):
    end = "<" if b[:2] == b"II" else ">"
    if len(b) < 8:
        raise InputError("TIFF shorter than its header")
    ifd = struct.unpack(end + "I", b[4:8])[0]
    if ifd + 2 > len(b):
        raise InputError(f"TIFF first directory at byte {ifd}, beyond the end of the file")
    n = struct.unpack(end + "H", b[ifd:ifd + 2])[0]
    tags = {}
    for k in range(n):
        e = ifd + 2 + 12 * k
        if e + 12 > len(b):
            break
        tag, typ, count = struct.unpack(end + "HHI", b[e:e + 8])
        if tag in (256, 257) and count == 1 and typ in (3, 4):   # ImageWidth, ImageLength as SHORT or LONG
            tags[tag] = struct.unpack(end + ("H" if typ == 3 else "I"), b[e + 8:e + (10 if typ == 3 else 12)])[0]
    if 256 not in tags or 257 not in tags:
        raise InputError("TIFF without ImageWidth and ImageLength in its first directory")
    return tags[256], tags[257]


def image_size(data: bytes):
    """(width, height) declared by the header of a PNG, JPEG or (classic) TIFF file; None for other formats.
    Raises InputError when the file starts as one of these but its header is malformed."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        return _png_size(data)
    if data[:3] == b"\xff\xd8\xff":
        return _jpeg_size(data)
    if data[:4] in (b"II*\x00", b"MM\x00*"):
        return _tiff_size(data)
    return None


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


def load_grey(path, expect_wh: tuple | None = None, max_pixels: int = MAX_IMAGE_PIXELS) -> np.ndarray:
    """Read an image file (PNG/JPEG/TIFF..., 8 or 16 bit, grey or colour) as float32 grey 0..255.

    ``expect_wh`` = (width, height): a file of another size is an ``ImageSizeError``, from its header when the
    format has one we read, before decoding. No image of more than ``max_pixels`` pixels is decoded."""
    p = Path(path)
    budget = max_pixels if expect_wh is None else min(max_pixels, int(expect_wh[0]) * int(expect_wh[1]))
    data = read_regular_file(p, "image file", RAW_BYTES_PER_PIXEL * budget + FILE_SLACK_BYTES)
    try:
        size = image_size(data)
    except InputError as e:
        raise InputError(f"cannot decode image {p} ({e})") from None
    if size is not None:
        _check_size(p, size, expect_wh, max_pixels)
    try:
        img = cv2.imdecode(np.frombuffer(data, np.uint8), cv2.IMREAD_UNCHANGED)
    except cv2.error as e:
        raise InputError(f"cannot decode image {p} ({str(e).strip().splitlines()[-1]})") from None
    if img is None:
        raise InputError(f"cannot decode image {p} (corrupt or unsupported format)")
    _check_size(p, (img.shape[1], img.shape[0]), expect_wh, max_pixels)
    return to_grey_f32(img)


def _check_size(p: Path, size: tuple, expect_wh, max_pixels: int) -> None:
    w, h = (int(x) for x in size)
    if expect_wh is not None and (w, h) != tuple(int(x) for x in expect_wh):
        raise ImageSizeError(f"image {p} is {w}x{h}, expected {expect_wh[0]}x{expect_wh[1]}", (w, h))
    if w * h > max_pixels:
        raise ImageSizeError(f"image {p} is {w}x{h} = {w * h} pixels, more than the {max_pixels} eonav decodes",
                             (w, h))
