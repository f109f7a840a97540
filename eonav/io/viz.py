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


# --------------------------------------------------------------------------------------------------
# the demo's picture: estimate and truth side by side, a colour bar in metres, obstacle boxes

BOX_BGR = (255, 255, 255)
TEXT_BGR = (255, 255, 255)
BAR_WIDTH_PX = 18


def nice_ticks_m(near_m: float, far_m: float) -> list[float]:
    """Round ranges between ``near_m`` and ``far_m`` (1-2-5 steps) for a colour bar's labels, both ends included."""
    out = [near_m]
    for decade in (1, 10, 100, 1000, 10000):
        for m in (1, 2, 5):
            v = m * decade
            if near_m * 1.3 < v < far_m / 1.3:
                out.append(float(v))
    return out + [far_m]


def colour_bar(height_px: int, near_m: float, far_m: float, label_width_px: int = 56) -> np.ndarray:
    """BGR colour bar of :func:`inverse_range_colours`' scale, ``near_m`` (red) at the top to ``far_m`` (blue) at
    the bottom, each row the colour of the range it is labelled with; ticks and labels in metres on its right."""
    import cv2
    rows = np.arange(height_px, dtype=np.float64)
    inv = 1.0 / near_m + (rows / max(height_px - 1, 1)) * (1.0 / far_m - 1.0 / near_m)
    col = inverse_range_colours((1.0 / inv).astype(np.float32)[:, None], np.ones((height_px, 1), bool), near_m, far_m)
    bar = np.zeros((height_px, BAR_WIDTH_PX + label_width_px, 3), np.uint8)
    bar[:, :BAR_WIDTH_PX] = col
    for r_m, y in bar_ticks(height_px, near_m, far_m):
        cv2.line(bar, (BAR_WIDTH_PX, y), (BAR_WIDTH_PX + 4, y), TEXT_BGR, 1)
        cv2.putText(bar, f"{r_m:g} m", (BAR_WIDTH_PX + 6, min(max(y + 4, 10), height_px - 2)),
                    cv2.FONT_HERSHEY_SIMPLEX, 0.38, TEXT_BGR, 1, cv2.LINE_AA)
    return bar


def bar_ticks(height_px: int, near_m: float, far_m: float, min_gap_px: int = 14) -> list[tuple[float, int]]:
    """(range_m, row) of the labels :func:`colour_bar` draws: :func:`nice_ticks_m` at least ``min_gap_px`` apart
    (one too close to the far end gives way to it)."""
    out = []
    for r_m in nice_ticks_m(near_m, far_m):
        y = int(round(bar_row(r_m, height_px, near_m, far_m)))
        if out and y - out[-1][1] < min_gap_px:
            if r_m != far_m or len(out) == 1:
                continue
            out.pop()
        out.append((r_m, y))
    return out


def bar_row(range_m: float, height_px: int, near_m: float, far_m: float) -> float:
    """The row of :func:`colour_bar` that shows ``range_m`` (linear in inverse range)."""
    t = (1.0 / near_m - 1.0 / range_m) / (1.0 / near_m - 1.0 / far_m)
    return float(np.clip(t, 0.0, 1.0)) * (height_px - 1)


def draw_obstacles(img: np.ndarray, obstacles, scale_x: float, scale_y: float) -> np.ndarray:
    """Each obstacle's ``bbox_px`` ([u_min, v_min, u_max, v_max] in frame pixels) as a box on ``img`` (pixels =
    frame pixels x scale), labelled with its ``distance_m``. Draws in place; returns ``img``."""
    import cv2
    for o in obstacles:
        u0, v0, u1, v1 = (float(x) for x in o["bbox_px"])
        p0 = (int(round(u0 * scale_x)), int(round(v0 * scale_y)))
        p1 = (int(round((u1 + 1) * scale_x)) - 1, int(round((v1 + 1) * scale_y)) - 1)
        cv2.rectangle(img, p0, p1, BOX_BGR, 1)
        label = f"{float(o['distance_m']):.1f} m"
        y = p0[1] - 3 if p0[1] >= 12 else p0[1] + 12          # above the box, or inside it at the top edge
        cv2.putText(img, label, (p0[0], y), cv2.FONT_HERSHEY_SIMPLEX, 0.4, (0, 0, 0), 3, cv2.LINE_AA)
        cv2.putText(img, label, (p0[0], y), cv2.FONT_HERSHEY_SIMPLEX, 0.4, TEXT_BGR, 1, cv2.LINE_AA)
    return img


def estimate_truth_picture(range_m: np.ndarray, valid: np.ndarray, truth_range_m: np.ndarray | None = None, *,
                           obstacles=(), frame_size: tuple[int, int] | None = None, near_m: float = 5.0,
                           far_m: float = 150.0, min_height_px: int = 384) -> tuple[np.ndarray, dict]:
    """BGR picture: the estimated range map (``valid`` pixels; black = no estimate), the truth beside it (when
    given; black = beyond ``far_m``), one colour scale from ``near_m`` (red) to ``far_m`` (blue) with its colour bar
    in metres on the right, and the obstacles (``bbox_px`` in frames of ``frame_size`` = (width, height), default the
    map's) boxed with their distance on both tiles. Maps are enlarged by a whole factor to at least
    ``min_height_px``. Returns the picture and its layout (``scale``, ``title_px``, ``tiles`` = x offsets of the
    tiles, ``bar_x``) for readers that check it."""
    import cv2
    r = np.asarray(range_m, np.float32)
    h, w = r.shape
    fw, fh = frame_size or (w, h)
    k = max(1, -(-min_height_px // h))
    tiles = [inverse_range_colours(r, np.asarray(valid, bool), near_m, far_m)]
    names = ["estimate"]
    if truth_range_m is not None:
        g = np.asarray(truth_range_m, np.float32)
        tiles.append(inverse_range_colours(g, np.isfinite(g) & (g > 0) & (g < far_m), near_m, far_m))
        names.append("truth")
    tiles = [cv2.resize(t, None, fx=k, fy=k, interpolation=cv2.INTER_NEAREST) for t in tiles]
    for t in tiles:
        draw_obstacles(t, obstacles, k * w / fw, k * h / fh)
    gap, title = 6, 20
    bar = colour_bar(h * k, near_m, far_m)
    width = len(tiles) * (w * k + gap) + bar.shape[1]
    pic = np.zeros((title + h * k, width, 3), np.uint8)
    xs = []
    for i, (t, name) in enumerate(zip(tiles, names)):
        x = i * (w * k + gap)
        xs.append(x)
        pic[title:, x:x + w * k] = t
        cv2.putText(pic, name, (x + 2, title - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.5, TEXT_BGR, 1, cv2.LINE_AA)
    bar_x = len(tiles) * (w * k + gap)
    pic[title:, bar_x:] = bar
    cv2.putText(pic, "range", (bar_x, title - 6), cv2.FONT_HERSHEY_SIMPLEX, 0.45, TEXT_BGR, 1, cv2.LINE_AA)
    return pic, {"scale": k, "title_px": title, "tiles": xs, "bar_x": bar_x}
