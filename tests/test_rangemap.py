"""The RangeResult contract (eonav.ranging.rangemap): what ``arrays()`` hands to an .npz file (``eonav locate
--out``, ``eonav fuse``) is each array under its own name, in the documented dtypes, and nothing for an array the
result does not carry. Against a hand-made result whose arrays all differ, so that one written under another's
name shows."""
from __future__ import annotations

import numpy as np

from eonav.ranging.rangemap import AT_INFINITY, FILLED, OCCLUDED, OUT_OF_VIEW, VALID, RangeResult


def hand_made(with_optional: bool = True) -> RangeResult:
    """2 x 3 pixels: a VALID one at 10 m (rho 0.1, sigma 0.01, confidence 10), one at infinity, one FILLED at 4 m,
    one occluded and two without an estimate; float64 inputs, so that the casts show."""
    rho = np.array([[0.1, 0.0, 0.25], [0.5, np.nan, np.nan]])
    std = np.array([[0.01, 0.002, 0.05], [0.02, np.inf, np.inf]])
    rng = np.array([[10.0, np.inf, 4.0], [np.nan, np.nan, np.nan]])
    conf = np.array([[10.0, 5.0, 5.0], [0.0, 0.0, 0.0]])
    flags = np.array([[VALID, VALID | AT_INFINITY, FILLED], [OUT_OF_VIEW | OCCLUDED, 0, 0]], np.int64)
    if not with_optional:
        return RangeResult(range_m=rng, confidence=conf, method="test")
    return RangeResult(range_m=rng, confidence=conf, method="test", inv_range_per_m=rho, inv_range_std_per_m=std,
                       flags=flags)


def test_arrays_are_each_under_their_own_name_in_the_documented_dtypes(tmp_path):
    res = hand_made()
    out = res.arrays()
    assert sorted(out) == ["confidence", "flags", "inv_range_per_m", "inv_range_std_per_m", "range_m"]
    for k in ("range_m", "confidence", "inv_range_per_m", "inv_range_std_per_m"):
        assert out[k].dtype == np.float32, k
        np.testing.assert_array_equal(out[k], getattr(res, k).astype(np.float32), err_msg=k)
    assert out["flags"].dtype == np.uint8
    np.testing.assert_array_equal(out["flags"], [[1, 33, 64], [136, 0, 0]])
    # the hand-made values themselves: sigma of the VALID pixel 0.01, of the FILLED one 0.05; rho 0.1 and 0.25
    assert out["inv_range_std_per_m"][0, 0] == np.float32(0.01) and out["inv_range_std_per_m"][0, 2] == np.float32(0.05)
    assert out["inv_range_per_m"][0, 0] == np.float32(0.1) and out["range_m"][0, 2] == np.float32(4.0)
    np.savez(tmp_path / "r.npz", **out)                       # what eonav locate --out writes
    with np.load(tmp_path / "r.npz") as z:
        want = np.float32([[0.01, 0.002, 0.05], [0.02, np.inf, np.inf]])
        np.testing.assert_array_equal(z["inv_range_std_per_m"], want)


def test_arrays_leave_out_what_the_result_does_not_carry():
    out = hand_made(with_optional=False).arrays()
    assert sorted(out) == ["confidence", "range_m"]
