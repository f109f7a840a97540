"""Fused per-pixel passes (numba) of the filter: the forward warp with its z-buffer and the crack closing
(``predict``), the Gaussian x uniform update (``update``) and the measurement's pose term (``measure``). The numpy
paths of those modules are the reference and do the same arithmetic in many full-array passes; these sweep the image
once, per row first the arithmetic of every cell in a branch-free loop (LLVM vectorises it; a cell it does not apply
to computes values never used), then the per-cell choices. tests/test_fusion.py and tests/test_pair_checks.py
compare the two.

Imported only when numba is installed (``eonav.ranging.methods._common.optional_kernels``); without it the numpy paths run.
"""
from __future__ import annotations

import math
from decimal import Decimal, localcontext

import numpy as np
from llvmlite import ir
from numba import njit
from numba.core import cgutils, types
from numba.extending import intrinsic

_JIT = dict(cache=True, fastmath=False, nogil=True, error_model="numpy")
# reciprocals, contractions and approximate functions allowed; not "no NaN / no inf" (empty cells are NaN)
_FAST = dict(_JIT, fastmath={"arcp", "contract", "afn"})
# contractions and approximate functions, divisions exact (a vectorised loop with "arcp" may multiply by a shared
# reciprocal instead: another rounding)
_CONTRACT = dict(_JIT, fastmath={"contract", "afn"})


@intrinsic
def _fma(typingctx, a, b, c):
    """a * b + c rounded once (llvm.fma: the instruction where the CPU has it)."""
    def codegen(context, builder, signature, args):
        d = ir.DoubleType()
        return builder.call(cgutils.get_or_insert_function(builder.module, ir.FunctionType(d, [d, d, d]),
                                                           "llvm.fma.f64"), args)
    return types.float64(types.float64, types.float64, types.float64), codegen


@intrinsic
def _bits(typingctx, x):
    """The bits of a float64 as an int64 (no conversion)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.IntType(64))
    return types.int64(types.float64), codegen


@intrinsic
def _from_bits(typingctx, i):
    """The float64 of the bits of an int64 (no conversion)."""
    def codegen(context, builder, signature, args):
        return builder.bitcast(args[0], ir.DoubleType())
    return types.float64(types.int64), codegen


def _exp2_table(n: int) -> np.ndarray:
    with localcontext() as ctx:
        ctx.prec = 40
        return np.array([float(Decimal(2) ** (Decimal(i) / n)) for i in range(n)])


# expf of glibc (sysdeps/ieee754/flt-32/e_expf.c, the FMA build; ARM optimized-routines): 2^(k/32) from a table
# times a cubic in double, within 0.502 ulp. The update's float32 exp inline instead of a libm call: cheaper, and
# the update's arithmetic loop vectorises with it (docs/methods.md, "Fusion over the stream": timing)
_EXP_N = 32
_EXP_TAB = _exp2_table(_EXP_N)
_EXP_C0 = float.fromhex("0x1.c6af84b912394p-5") / _EXP_N ** 3
_EXP_C1 = float.fromhex("0x1.ebfce50fac4f3p-3") / _EXP_N ** 2
_EXP_C2 = float.fromhex("0x1.62e42ff0c52d6p-1") / _EXP_N
_EXP_INV_LN2_N = float.fromhex("0x1.71547652b82fep+0") * _EXP_N
_EXP_SHIFT = float.fromhex("0x1.8p+52")                 # adding it rounds to an integer
_EXP_SHIFT_BITS = int(np.float64(_EXP_SHIFT).view(np.int64))
_EXP_UNDERFLOW = np.float32(float.fromhex("-0x1.9fe368p6"))   # log(2^-150): below it exp rounds to 0


@njit(**_JIT)
def exp_nonpositive(x):
    """exp(x) of a float32 x <= 0 (NaN: NaN), the same float32 as glibc's expf with FMA. Branch-free (the argument
    clamped, the special cases selected at the end) so that a loop calling it vectorises."""
    ok = x >= _EXP_UNDERFLOW
    xd = np.float64(x) if ok else np.float64(_EXP_UNDERFLOW)
    z = _fma(_EXP_INV_LN2_N, xd, _EXP_SHIFT)                 # k = round(x * 32 / ln 2) in z's low bits
    kd = z - _EXP_SHIFT
    r = _fma(_EXP_INV_LN2_N, xd, -kd)                        # x * 32 / ln 2 - k, |r| <= 1/2
    k = _bits(z) - _EXP_SHIFT_BITS
    # 2^(k / 32) = 2^((k & 31) / 32) from the table times 2^(k >> 5), added to its exponent (exact: a normal double)
    sc = _from_bits(_bits(_EXP_TAB[k & (_EXP_N - 1)]) + ((k >> 5) << 52))
    y = np.float32(_fma(_fma(_EXP_C0, r, _EXP_C1), r * r, _fma(_EXP_C2, r, 1.0)) * sc)
    return y if ok else (x + x if x != x else np.float32(0.0))


@njit(**_JIT)
def warp(rho, var, a, b, n, du, dv, flags, R, t, cam0, cam1, q, q_abs,
         o_rho, o_var, o_a, o_b, o_n, o_du, o_dv, o_flags):
    """Every occupied source cell's point into the new grid (predict's module docstring): the output arrays are
    emptied (any contents: a reused state; C-contiguous); where several points land on one pixel the largest
    rho_new wins (the first of equal ones). cam0, cam1: (fx, fy, cx, cy) of the source and the new camera. Returns the number of
    cells written. The output rows are emptied as the scatter first reaches them (``_clear_rows``; the rest at the
    end), not all up front: a state larger than the core's cache then takes its empty values while the rows the
    points land in are still cached (a motion moves points by a few rows), not once more from memory."""
    h, w = rho.shape
    h1, w1 = o_rho.shape
    cleared = 0                  # output rows [0, cleared) emptied so far
    f32 = np.float32
    fx0, fy0, cx0, cy0 = cam0[0], cam0[1], cam0[2], cam0[3]
    fx1, fy1, cx1, cy1 = cam1[0], cam1[1], cam1[2], cam1[3]
    # the rotation and the thresholds as float32 locals (no reloads, no float64 comparisons per pixel)
    r00, r01, r02 = R[0, 0], R[0, 1], R[0, 2]
    r10, r11, r12 = R[1, 0], R[1, 1], R[1, 2]
    r20, r21, r22 = R[2, 0], R[2, 1], R[2, 2]
    t0, t1, t2 = t[0], t[1], t[2]
    eps = f32(1e-3)
    half = f32(0.5)
    zero = f32(0.0)
    wmax = f32(w1 - 1)
    hmax = f32(h1 - 1)
    # per row: the transfer of every cell into row buffers in a branch-free loop (LLVM vectorises it), with the flat
    # index of its target pixel (-1: none), then the scatter of the valid ones into the flat outputs
    buf = np.empty((4, w), np.float32)
    b_du, b_dv, b_rn, b_var = buf[0], buf[1], buf[2], buf[3]
    b_tgt = np.empty(w, np.int32)            # (int32 and the columns as float32 loads, not int64 conversions
    colf = np.arange(w).astype(np.float32)   # per cell: LLVM then vectorises the loop 8 cells wide)
    w1i = np.int32(w1)
    # (views: the outputs must be C-contiguous, reshape raises otherwise; predict makes sure they are)
    f_rho, f_var, f_a, f_b = o_rho.reshape(-1), o_var.reshape(-1), o_a.reshape(-1), o_b.reshape(-1)
    f_n, f_du, f_dv, f_flags = o_n.reshape(-1), o_du.reshape(-1), o_dv.reshape(-1), o_flags.reshape(-1)
    written = 0
    for y in range(h):
        fy = f32(y)
        for x in range(w):
            r = rho[y, x]
            m1 = (colf[x] + du[y, x] - cx0) / fx0
            m2 = (fy + dv[y, x] - cy0) / fy0
            A0 = r00 + r01 * m1 + r02 * m2
            A1 = r10 + r11 * m1 + r12 * m2
            A2 = r20 + r21 * m1 + r22 * m2
            den = A0 + t0 * r
            inv = f32(1.0) / den
            un = cx1 + fx1 * (A1 + t1 * r) * inv
            vn = cy1 + fy1 * (A2 + t2 * r) * inv
            ui = np.floor(un + half)      # nearest pixel (halves up, as predict)
            vi = np.floor(vn + half)
            rn = r * inv
            j = A0 * inv * inv
            ok = (math.isfinite(r) and den > eps and A0 > eps
                  and ui >= zero and ui <= wmax and vi >= zero and vi <= hmax)
            b_tgt[x] = np.int32(vi) * w1i + np.int32(ui) if ok else np.int32(-1)
            b_du[x] = un - ui
            b_dv[x] = vn - vi
            b_rn[x] = rn
            b_var[x] = var[y, x] * j * j + q * rn * rn + q_abs
        top = -1                          # the row's farthest target row
        for x in range(w):
            T = b_tgt[x]
            if T > top:
                top = T
        if top >= 0 and top // w1 >= cleared:
            _clear_rows(o_rho, o_var, o_a, o_b, o_n, o_du, o_dv, o_flags, cleared, top // w1 + 1)
            cleared = top // w1 + 1
        for x in range(w):
            T = b_tgt[x]
            if T < 0:
                continue
            rn = b_rn[x]
            cur = f_rho[T]
            if cur == cur:                # occupied already: the nearer point wins
                if not rn > cur:
                    continue
            else:
                written += 1
            f_rho[T] = rn
            f_var[T] = b_var[x]
            f_a[T] = a[y, x]
            f_b[T] = b[y, x]
            f_n[T] = n[y, x]
            f_flags[T] = flags[y, x]
            f_du[T] = b_du[x]
            f_dv[T] = b_dv[x]
    _clear_rows(o_rho, o_var, o_a, o_b, o_n, o_du, o_dv, o_flags, cleared, h1)
    return written


@njit(**_JIT)
def _clear_rows(o_rho, o_var, o_a, o_b, o_n, o_du, o_dv, o_flags, y0, y1):
    """Rows y0 .. y1 - 1 of the warp's outputs emptied (contiguous fills)."""
    if y1 <= y0:
        return
    o_rho[y0:y1] = np.nan
    o_var[y0:y1] = np.inf
    o_a[y0:y1] = 0.0
    o_b[y0:y1] = 0.0
    o_n[y0:y1] = 0
    o_du[y0:y1] = 0.0
    o_dv[y0:y1] = 0.0
    o_flags[y0:y1] = 0


@njit(**_JIT)
def close_cracks(rho, var, a, b, n, du, dv, flags, k2):
    """predict.close_cracks (horizontal neighbours first, then vertical) in one sweep over the rows: row y closed
    across, then row y - 1 down (its neighbours' rows are final across by then). The same cells and values as two
    passes: a cell closed in one axis had an empty neighbour in it, so no other cell of that axis used it.
    Returns the count."""
    h, w = rho.shape
    closed = 0
    todo = np.empty(w, np.bool_)
    for y in range(h):
        closed += _close_row(rho, var, a, b, n, du, dv, flags, k2, y, 0, 1, 1, w - 1, todo)
        if y >= 2:
            closed += _close_row(rho, var, a, b, n, du, dv, flags, k2, y - 1, 1, 0, 0, w, todo)
    return closed


@njit(**_JIT)
def _close_row(rho, var, a, b, n, du, dv, flags, k2, y, oy, ox, x0, x1, todo):
    """The cracks of row y between its neighbours (y - oy, x - ox) and (y + oy, x + ox), columns x0..x1 - 1:
    which first (branch-free: vectorised), then those closed. Returns the count."""
    ya, yb = y - oy, y + oy
    for x in range(x0, x1):
        d = rho[yb, x + ox] - rho[ya, x - ox]
        todo[x] = (not math.isfinite(rho[y, x])) & (d * d <= k2 * (var[ya, x - ox] + var[yb, x + ox]))
    closed = 0
    for x in range(x0, x1):
        if not todo[x]:
            continue
        xa, xb = x - ox, x + ox
        d = rho[yb, xb] - rho[ya, xa]
        rho[y, x] = np.float32(0.5) * (rho[ya, xa] + rho[yb, xb])
        var[y, x] = max(var[ya, xa], var[yb, xb]) + np.float32(0.25) * d * d
        a[y, x] = min(a[ya, xa], a[yb, xb])
        b[y, x] = max(b[ya, xa], b[yb, xb])
        n[y, x] = min(n[ya, xa], n[yb, xb])
        flags[y, x] = flags[ya, xa] & flags[yb, xb]
        du[y, x] = 0.0
        dv[y, x] = 0.0
        closed += 1
    return closed


@njit(**_FAST)
def update(rho, var, a, b, n, du, dv, flags, rho_m, std_m, flags_m, bits, prm):
    """update.update's arithmetic in place: every pixel's flags taken from the measurement's, and each measured one
    (``update.measured``; bits: VALID | FILLED, VALID, WEAK_BITS (0: no weak measurements), ILL_CONDITIONED) fused.
    prm: float32 (max_rel_std, sigma_scale, rho_max, a_init, b_init, evidence_cap, eta_outlier, b_min). Returns (measured,
    started, inliers, outliers, restarted)."""
    cnt = np.zeros(5, np.int64)
    buf = np.empty((6, rho.shape[1]), np.float32)
    for y in range(rho.shape[0]):
        _update_row(y, rho, var, a, b, n, du, dv, flags, rho_m, std_m, flags_m, bits, prm, cnt, buf)
    return cnt[0], cnt[1], cnt[2], cnt[3], cnt[4]


@njit(**_FAST)
def update_classify(rho, var, a, b, n, du, dv, flags, rho_m, std_m, flags_m, bits, prm,
                    cbits, eta_inlier, max_rel_std, rho_far, slant2, held, o_rho, o_std, o_flags, o_rng, o_conf,
                    o_exclude):
    """``update`` then ``classify_state`` in one sweep: row y-1 is classified once row y is updated (its slant
    term needs its neighbours' rows), so the state is read once. Returns the five update counts then the five
    classification counts."""
    h = rho.shape[0]
    cnt = np.zeros(5, np.int64)
    cc = np.zeros(5, np.int64)
    buf = np.empty((7, rho.shape[1]), np.float32)
    for y in range(h):
        _update_row(y, rho, var, a, b, n, du, dv, flags, rho_m, std_m, flags_m, bits, prm, cnt, buf)
        if y >= 1:
            _classify_row(y - 1, rho, var, a, b, n, flags, cbits, eta_inlier, max_rel_std, rho_far, slant2, held,
                          o_rho, o_std, o_flags, o_rng, o_conf, o_exclude, cc, buf[6])
    _classify_row(h - 1, rho, var, a, b, n, flags, cbits, eta_inlier, max_rel_std, rho_far, slant2, held,
                  o_rho, o_std, o_flags, o_rng, o_conf, o_exclude, cc, buf[6])
    return cnt[0], cnt[1], cnt[2], cnt[3], cnt[4], cc[0], cc[1], cc[2], cc[3], cc[4]


@njit(**_FAST)
def _start_cell(y, x, rho, var, a, b, n, du, dv, xm, tau2, a_init, b_init):
    """Cell (y, x) starts afresh from one measurement: an empty cell, or one whose inlier ratio fell below the
    outlier threshold (it diverged)."""
    rho[y, x] = xm
    var[y, x] = tau2
    a[y, x] = a_init
    b[y, x] = b_init
    n[y, x] = 1
    du[y, x] = 0.0
    dv[y, x] = 0.0


@njit(**_FAST)
def _update_row(y, rho, var, a, b, n, du, dv, flags, rho_m, std_m, flags_m, bits, prm, cnt, buf):
    """One row of ``update``; cnt (int64[5]) gains its counts. First the update's arithmetic for every cell of the
    row into buf (float32[6, w]) in a branch-free loop, which LLVM vectorises (a cell it does not apply to computes
    garbage, never used), then per cell which of it applies."""
    w = rho.shape[1]
    max_rel_std, s, rho_max, a_init, b_init, cap, eta_outlier = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5], prm[6]
    b_min = prm[7]
    inv_u = np.float32(1.0) / rho_max
    inv_2pi = np.float32(1.0 / (2.0 * math.pi))
    one = np.float32(1.0)
    b_mu, b_s2, b_a, b_b, b_c1, b_t2 = buf[0], buf[1], buf[2], buf[3], buf[4], buf[5]
    for x in range(w):               # the exp (float64 inside) in a loop of its own: the rest vectorises wider
        tau = std_m[y, x] * s
        tau2 = tau * tau
        b_t2[x] = tau2               # (a second use of tau^2, as below: S rounded as there, not contracted)
        S = var[y, x] + tau2
        iS = one / S
        d = rho_m[y, x] - rho[y, x]
        b_c1[x] = exp_nonpositive(np.float32(-0.5) * d * d * iS)
    for x in range(w):
        tau = std_m[y, x] * s
        tau2 = tau * tau
        mu = rho[y, x]
        s2 = var[y, x]
        A = a[y, x]
        B = b[y, x]
        # (the update's arithmetic with its divisions shared: 1 / S, 1 / (A + B), 1 / (A + B + 1), 1 / f)
        S = s2 + tau2
        iS = one / S
        d = rho_m[y, x] - mu
        iab = one / (A + B)
        c1 = A * iab * b_c1[x] * np.sqrt(iS * inv_2pi)
        c2 = B * iab * inv_u
        c1 = c1 / (c1 + c2)
        c2 = one - c1
        g = s2 * iS                                  # s'^2 / tau^2
        sp2 = g * tau2
        m = mu + g * d
        dm = m - mu
        ab1 = A + B + one
        iab1 = one / ab1
        f = (c1 * (A + one) + c2 * A) * iab1
        e = (c1 * (A + one) * (A + np.float32(2.0)) + c2 * A * (A + one)) * iab1 / (ab1 + one)
        i_f = one / f
        a_new = (e - f) / (f - e * i_f)
        b_new = a_new * (one - f) * i_f
        tot = a_new + b_new
        k = cap / tot if tot > cap else one
        b_mu[x] = c1 * m + c2 * mu
        b_s2[x] = c1 * sp2 + c2 * s2 + c1 * c2 * dm * dm
        b_a[x] = a_new * k
        b_b[x] = max(b_new * k, b_min)
        b_c1[x] = c1
    n_meas = started = inl = outl = rest = 0     # (local counters: stores to cnt would be reloaded per cell)
    weak_bits, weak_want, two = bits[2], bits[3], np.float32(2.0)
    for x in range(w):                           # (branch-free select and store: vectorised)
        fm = flags_m[y, x]
        flags[y, x] = fm
        xm = rho_m[y, x]
        sd = std_m[y, x]
        weak = (weak_bits != 0) & ((fm & weak_bits) == weak_want) & ~((sd <= max_rel_std * xm) & (xm >= two * sd))
        meas = math.isfinite(xm) & math.isfinite(sd) & (sd > 0) & (((fm & bits[0]) == bits[1]) | weak)
        tau = sd * s
        tau2 = tau * tau
        occ = math.isfinite(rho[y, x])
        a_new = b_a[x]
        b_new = b_b[x]
        diverged = a_new / (a_new + b_new) < eta_outlier
        start = meas & (~occ | diverged)
        fuse = meas & occ & ~diverged
        n_meas += meas
        started += meas & ~occ
        inl += meas & occ & (b_c1[x] > 0.5)
        outl += meas & occ & ~(b_c1[x] > 0.5)
        rest += meas & occ & diverged
        nn = n[y, x]
        rho[y, x] = xm if start else (b_mu[x] if fuse else rho[y, x])
        var[y, x] = tau2 if start else (b_s2[x] if fuse else var[y, x])
        a[y, x] = a_init if start else (a_new if fuse else a[y, x])
        b[y, x] = b_init if start else (b_new if fuse else b[y, x])
        n[y, x] = 1 if start else (nn + (nn < 65535) if fuse else nn)
        du[y, x] = 0.0 if start else du[y, x]
        dv[y, x] = 0.0 if start else dv[y, x]
    cnt[0] += n_meas
    cnt[1] += started
    cnt[2] += inl
    cnt[3] += outl
    cnt[4] += rest


@njit(**_FAST)
def classify_state(rho, var, a, b, n, flags, bits, eta_inlier, max_rel_std, rho_far, slant2, held,
                   o_rho, o_std, o_flags, o_rng, o_conf, o_exclude):
    """fused_map's arrays in one pass: o_rho = rho, o_std = sqrt(var + slant2 * g2) (g2: ``slant_g2``), the flags
    of fused_map and the rules of ``eonav.ranging.methods._common.classify_into`` (the same float32 arithmetic),
    o_exclude = occupied cells whose evidence disagrees; with ``held`` the held single cells (``fused_map.held_single``)
    reported without a range, as ``fused_map._demote_held``. bits: uint8 (reason bits kept for empty cells,
    ILL_CONDITIONED, OUT_OF_VIEW | LOW_TEXTURE | ILL_CONDITIONED | TRUNCATION, AT_INFINITY, VALID, VALID | FILLED,
    OUT_OF_VIEW) of ``eonav.ranging.rangemap``. Returns (n_valid, n_at_infinity, n_occupied, n_disagree, n_held)."""
    cc = np.zeros(5, np.int64)
    g2 = np.empty(rho.shape[1], np.float32)
    for y in range(rho.shape[0]):
        _classify_row(y, rho, var, a, b, n, flags, bits, eta_inlier, max_rel_std, rho_far, slant2, held,
                      o_rho, o_std, o_flags, o_rng, o_conf, o_exclude, cc, g2)
    return cc[0], cc[1], cc[2], cc[3], cc[4]


@njit(**_CONTRACT)
def _classify_row(y, rho, var, a, b, n, flags, bits, eta_inlier, max_rel_std, rho_far, slant2, held,
                  o_rho, o_std, o_flags, o_rng, o_conf, o_exclude, cc, g2):
    """One row of ``classify_state``; cc (int64[5]) gains its counts; g2 (float32[w]): room for the row's
    ``slant_g2``."""
    w = rho.shape[1]
    _slant_row(rho, var, y, g2)
    reason_bits, ILL, BAD, INF, VAL, VF, OOV = bits[0], bits[1], bits[2], bits[3], bits[4], bits[5], bits[6]
    two_f = np.float32(2.0)
    n_val = n_inf = n_occ = n_dis = n_held = n_held_inf = 0    # (local counters, as _update_row's)
    for x in range(w):
        r = rho[y, x]
        o_rho[y, x] = r
        occ = math.isfinite(r)
        if occ:
            n_occ += 1
            A = a[y, x]
            agree = A >= eta_inlier * (A + b[y, x])
            f = np.uint8(0) if agree else ILL
            sd = np.float32(math.sqrt(var[y, x] + slant2 * g2[x]))
            if not agree:
                n_dis += 1
        else:
            agree = False
            f = flags[y, x] & reason_bits
            if f == 0:
                f = ILL
            sd = np.float32(math.sqrt(var[y, x]))
        o_std[y, x] = sd
        o_exclude[y, x] = occ and not agree
        two = two_f * sd
        near0 = r < two
        inf_ok = (two < rho_far) and near0
        good = ((sd / r <= max_rel_std) and not near0) or inf_ok
        good = good and occ and math.isfinite(sd)
        if not good:
            f |= ILL
        ok = (f & BAD) == 0
        rng = np.float32(np.nan)
        conf = np.float32(0.0)
        if ok and inf_ok:
            f |= INF | VAL
            n_inf += 1
            rng = np.float32(np.inf)
            conf = max(np.float32(rho_far) / sd, np.float32(0.0))
        elif ok:
            f |= VAL
            n_val += 1
            rng = np.float32(1.0) / abs(r)
            conf = max(r / sd, np.float32(0.0))
        # a held single cell (one measurement, the last pair looked and did not range it) reported VALID: no range
        # (branch-free: which cells are held is irregular, a branch on it is mispredicted)
        last = flags[y, x]
        hc = held & ok & (n[y, x] == 1) & ((last & VF) != VAL) & ((last & OOV) == 0)
        n_held += hc
        n_held_inf += hc & inf_ok
        o_flags[y, x] = ILL if hc else f
        o_rng[y, x] = np.float32(np.nan) if hc else rng
        o_conf[y, x] = np.float32(0.0) if hc else conf
    cc[0] += n_val - (n_held - n_held_inf)
    cc[1] += n_inf - n_held_inf
    cc[2] += n_occ
    cc[3] += n_dis
    cc[4] += n_held


@njit(**_FAST)
def _slant_row(rho, var, y, g2):
    """``slant_g2`` of every cell of row y into g2: the inner columns in one branch-free loop over contiguous
    neighbours (vectorised), the two border columns by ``slant_g2`` itself."""
    h, w = rho.shape
    nan = np.float32(np.nan)
    zero = np.float32(0.0)
    yu, yd = max(y - 1, 0), min(y + 1, h - 1)
    up, down = y > 0, y < h - 1
    for x in range(1, w - 1):
        r = rho[y, x]
        d = rho[y, x - 1] - r
        el = d * d
        d = rho[y, x + 1] - r
        er = d * d
        d = rho[yu, x] - r
        eu = d * d if up else nan
        d = rho[yd, x] - r
        ed = d * d if down else nan
        g2[x] = np.fmax(np.fmin(el, er), zero) + np.fmax(np.fmin(eu, ed), zero)
    if w > 0:
        g2[0] = slant_g2(rho, var, y, 0)
        g2[w - 1] = slant_g2(rho, var, y, w - 1)


@njit(**_FAST)
def slant_g2(rho, var, y, x):
    """The squared inverse-range gradient (1/m per pixel)^2 of the surface cell (y, x) lies on: per axis the
    smaller of its two one-sided squared differences (the side across a depth edge is not its surface); a side with
    an empty neighbour (NaN) or outside the image is not used, an axis with none contributes 0. (Not less the two
    cells' noise: neighbours share most of their windows, their errors are nearly the same.)
    Branch-free (fmin / fmax skip NaN): which side is smaller is noise, a branch on it is mispredicted."""
    h, w = rho.shape
    r = rho[y, x]
    nan = np.float32(np.nan)
    x0, x1, y0, y1 = max(x - 1, 0), min(x + 1, w - 1), max(y - 1, 0), min(y + 1, h - 1)
    d = rho[y, x0] - r
    el = d * d
    d = rho[y, x1] - r
    er = d * d
    d = rho[y0, x] - r
    eu = d * d
    d = rho[y1, x] - r
    ed = d * d
    if x == 0:
        el = nan
    if x == w - 1:
        er = nan
    if y == 0:
        eu = nan
    if y == h - 1:
        ed = nan
    return np.fmax(np.fmin(el, er), np.float32(0.0)) + np.fmax(np.fmin(eu, ed), np.float32(0.0))


@njit(**_JIT)
def prior_arrays(rho, var, a, b, n, eta_inlier, n_min, o_rho, o_std):
    """The state as the dense method's prior (``eonav.fusion.sequence``): rho and its sigma where the cell holds an
    estimate of at least n_min measurements whose evidence agrees (E[inlier ratio] >= eta_inlier), else NaN / inf.
    Returns the number of such cells."""
    cnt = 0
    for y in range(rho.shape[0]):
        for x in range(rho.shape[1]):
            r = rho[y, x]
            A = a[y, x]
            if r == r and n[y, x] >= n_min and A >= eta_inlier * (A + b[y, x]):
                o_rho[y, x] = r
                o_std[y, x] = np.float32(math.sqrt(var[y, x]))
                cnt += 1
            else:
                o_rho[y, x] = np.float32(np.nan)
                o_std[y, x] = np.float32(np.inf)
    return cnt


@njit(**_JIT)
def pose_sigma(rho, std, ra, ca, B, fxb, fyb, s):
    """``eonav.fusion.measure.add_pose_sigma`` in one branch-free pass, in place on std: sigma^2 += (s den^2 / |C|)^2
    where rho and sigma are finite and den = A0 + B0 rho > 0. The epipolar map's A_i = ra[i, x] + ca[i, y] (its row
    and column parts, float32, as ``EpipolarMap.build`` sums them) and C per pixel, in the numpy path's float32 order
    (no fastmath), |C| as glibc's hypotf computes it: the same values bit for bit (tests/test_pair_checks.py), and a
    loop LLVM vectorises (a libm hypotf call per pixel took 3 x as long)."""
    B0, B1, B2 = B[0], B[1], B[2]
    for y in range(rho.shape[0]):
        a0, a1, a2 = ca[0, y], ca[1, y], ca[2, y]
        for x in range(rho.shape[1]):
            r = rho[y, x]
            sd = std[y, x]
            A0 = ra[0, x] + a0
            den = A0 + B0 * r
            c1 = fxb * (B1 * A0 - B0 * (ra[1, x] + a1))
            c2 = fyb * (B2 * A0 - B0 * (ra[2, x] + a2))
            # |C| as glibc's hypotf: the float64 sum of the exact squares, its root rounded to float32
            hc = np.float32(math.sqrt(np.float64(c1) * np.float64(c1) + np.float64(c2) * np.float64(c2)))
            e = s * den * den / hc
            new = np.sqrt(sd * sd + e * e)
            ok = np.isfinite(r) and np.isfinite(sd) and den > 0
            std[y, x] = new if ok else sd
