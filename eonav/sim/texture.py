"""Band-limited procedural texture evaluated in world (or face) coordinates, in metres.

The texture is a sum of octaves. Every octave is a bilinear lookup of one precomputed periodic tile
whose spectrum is a single raised-cosine octave band: the bands of successive octaves (factor 2 in
wavelength) add up to a flat partition of the spectrum, so the sum has energy at all scales between
``LAMBDA_MIN_M`` and the coarsest octave. Each octave is rotated and offset differently (seeded), so
the tile's periodicity does not show.

Anti-aliasing by frequency clamping: an octave fades out where its shortest wavelength falls below a
few pixel footprints (``footprint_m``: metres of surface per pixel). This is what the box filter of a real
pixel does, and it keeps two views of the same surface consistent instead of aliased.

The value is a deterministic function of (coordinates, footprint, seed): two views of one scene see the
same texture at the same world point.
"""
from __future__ import annotations

from functools import lru_cache

import cv2
import numpy as np

TILE_N = 512                  # tile side in texels (power of two)
TILE_F0_CYCLES = 16.0         # band centre, cycles per tile: centre wavelength = TILE_N / TILE_F0 = 32 texels
TEXELS_PER_LAMBDA = TILE_N / TILE_F0_CYCLES
LAMBDA_MIN_M = 0.02           # centre wavelength of the finest octave
N_OCTAVES = 12                # 0.02 m .. 41 m centre wavelengths
AMP_EXPONENT = 0.3            # octave amplitude ~ lambda^0.3: fine detail stays strong (direct methods need it)
FADE_LO_PX, FADE_HI_PX = 2.5, 5.0   # octave weight 0 below, 1 above, centre wavelength in footprints


N_TILES = 4                   # distinct tiles; every seed still gets its own octave rotations and offsets


@lru_cache(maxsize=N_TILES)
def noise_tile(seed: int) -> np.ndarray:
    """Periodic TILE_N x TILE_N float32 tile, zero mean, unit std, spectrum one raised-cosine octave band
    (radial frequency TILE_F0/2 .. 2*TILE_F0 cycles per tile, weight cos^2(pi/2 log2(f/f0)))."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x7E47]))
    white = rng.standard_normal((TILE_N, TILE_N))
    fy = np.fft.fftfreq(TILE_N) * TILE_N
    fx = np.fft.rfftfreq(TILE_N) * TILE_N
    f = np.hypot(fy[:, None], fx[None, :])
    with np.errstate(divide="ignore"):
        octave = np.log2(np.maximum(f, 1e-9) / TILE_F0_CYCLES)
    band = np.where(np.abs(octave) < 1.0, np.cos(0.5 * np.pi * np.clip(octave, -1, 1)), 0.0)   # power is cos^2
    tile = np.fft.irfft2(np.fft.rfft2(white) * band, s=(TILE_N, TILE_N))
    tile -= tile.mean()
    tile /= tile.std()
    tile = tile.astype(np.float32)
    tile.setflags(write=False)
    return tile


def bilinear_wrap(tile: np.ndarray, x_texel: np.ndarray, y_texel: np.ndarray) -> np.ndarray:
    """Bilinear lookup of a periodic square tile at float texel coordinates (1-D float32 arrays).

    cv2.remap with BORDER_WRAP does the gather (coordinates may lie outside the tile; keep them within
    +-65536 texels so float32 keeps sub-texel precision: see ``_wrap``)."""
    size = x_texel.size
    width = 1024
    if size % width:
        rows = size // width + 1
        mx = np.zeros(rows * width, np.float32)
        my = np.zeros(rows * width, np.float32)
        mx[:size] = x_texel
        my[:size] = y_texel
    else:
        rows = size // width
        mx = np.asarray(x_texel, np.float32)
        my = np.asarray(y_texel, np.float32)
    out = cv2.remap(tile, mx.reshape(rows, width), my.reshape(rows, width), cv2.INTER_LINEAR,
                    borderMode=cv2.BORDER_WRAP)
    return out.ravel()[:size]


def _wrap(t: np.ndarray, n: int, needed: bool) -> np.ndarray:
    """float64 texel coordinates -> float32, wrapped into [0, n) when they could lose precision."""
    if needed:
        t = t - n * np.floor(t * (1.0 / n))
    return t.astype(np.float32)


@lru_cache(maxsize=32)
def _octave_params(seed: int):
    """Per-octave (centre wavelength m, amplitude, cos, sin, offset x, offset y), seeded."""
    rng = np.random.default_rng(np.random.SeedSequence([int(seed), 0x0C7A]))
    lam = LAMBDA_MIN_M * 2.0 ** np.arange(N_OCTAVES)
    amp = lam ** AMP_EXPONENT
    amp /= np.sqrt(np.sum(amp ** 2))
    ang = rng.uniform(0, 2 * np.pi, N_OCTAVES)
    off = rng.uniform(0, TILE_N, (N_OCTAVES, 2))
    return tuple((float(lam[k]), float(amp[k]), float(np.cos(ang[k])), float(np.sin(ang[k])),
                  float(off[k, 0]), float(off[k, 1])) for k in range(N_OCTAVES))


def octave_weight(lambda_m: float, inv_footprint: np.ndarray) -> np.ndarray:
    """Frequency clamp: 0 where the octave's centre wavelength is < FADE_LO_PX footprints, 1 above FADE_HI_PX,
    smoothstep between. ``inv_footprint``: pixels per surface metre (float32)."""
    scale = np.float32(lambda_m / (FADE_HI_PX - FADE_LO_PX))
    shift = np.float32(FADE_LO_PX / (FADE_HI_PX - FADE_LO_PX))
    s = inv_footprint * scale - shift
    np.clip(s, 0.0, 1.0, out=s)
    return s * s * (3 - 2 * s)


def fractal_noise(x_m: np.ndarray, y_m: np.ndarray, footprint_m: np.ndarray, seed: int,
                  min_lambda_m: float = LAMBDA_MIN_M, max_lambda_m: float = np.inf) -> np.ndarray:
    """Multi-octave band-limited noise at surface coordinates (x_m, y_m) (1-D arrays, metres).

    ``footprint_m``: surface metres per pixel at each point (frequency clamp). Unclamped std ~1.
    Octaves outside [min_lambda_m, max_lambda_m] (centre wavelengths) are left out.
    """
    x_m = np.asarray(x_m, np.float64).ravel()
    y_m = np.asarray(y_m, np.float64).ravel()
    out = np.zeros(x_m.shape, np.float32)
    if x_m.size == 0:
        return out
    inv_fp = (1.0 / np.asarray(footprint_m, np.float32)).ravel()
    fp_min, fp_max = float(1.0 / inv_fp.max()), float(1.0 / inv_fp.min())
    extent = float(max(np.abs(x_m).max(), np.abs(y_m).max()))
    tile = noise_tile(int(seed) % N_TILES)
    for lam, amp, c, s, ox, oy in _octave_params(seed):
        if lam < min_lambda_m * 0.999 or lam > max_lambda_m * 1.001:
            continue
        if lam <= FADE_LO_PX * fp_min:
            continue                                  # faded out everywhere
        if lam >= FADE_HI_PX * fp_max:                # fully on everywhere
            xs, ys, ws, idx = x_m, y_m, None, slice(None)
        else:
            w = octave_weight(lam, inv_fp)
            sel = np.flatnonzero(w > 0)
            xs, ys, ws, idx = x_m[sel], y_m[sel], w[sel], sel
        k = TEXELS_PER_LAMBDA / lam
        far = k * extent * 1.5 + TILE_N > 65536.0
        tx = _wrap((c * k) * xs - (s * k) * ys + ox, TILE_N, far)
        ty = _wrap((s * k) * xs + (c * k) * ys + oy, TILE_N, far)
        val = bilinear_wrap(tile, tx, ty) * np.float32(amp)
        if ws is not None:
            val *= ws
        out[idx] += val
    return out
