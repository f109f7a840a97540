"""A state's n counts instants (``FusionConfig.n_per_instant``): a rig frame's motion and stereo measurements of one
cell count once, so the held-single rule withdraws a cell both pairs of one frame ranged and no later frame repeated
(docs/methods.md, "Fusion over the stream"; docs/guidance.md, "The rig's false tracks")."""
from types import SimpleNamespace

import numpy as np
import pytest

from eonav.fusion.fused_map import MapConfig, update_and_map
from eonav.fusion.sequence import FusionConfig, FusionRunner
from eonav.fusion.state import InverseRangeState, optional_kernels
from eonav.fusion.update import UpdateConfig, _start_cells, update
from eonav.ranging.rangemap import ILL_CONDITIONED, LOW_TEXTURE, VALID
from tests.test_fusion import cam, pose

PATHS = [False] + ([True] if optional_kernels() is not None else [])
MAP = MapConfig(fill=False)
RHO, STD = 0.04, 2e-3           # 25 m, 5 %


def runner(on=True, cols=6):
    r = FusionRunner(FusionConfig(n_per_instant=on))
    r.states["nose"] = InverseRangeState.empty(cam(cols, 2), pose(), 0.0)
    return r


def meas(shape, flags_by_col):
    """A measurement: every cell 25 m, 5 %, its flags per column."""
    fl = np.zeros(shape, np.uint8)
    for c, f in enumerate(flags_by_col):
        fl[:, c] = f
    return np.full(shape, RHO, np.float32), np.full(shape, STD, np.float32), fl


def instant(r, seq, flag_rows, kernels, restart=None, arrival=False):
    """One frame of the reference camera measured ``len(flag_rows)`` times (a rig: motion then stereo), as
    ``FusionRunner.push`` does: each measurement's update (the last with its map) and the instant's count.
    ``restart``: columns the first measurement restarts (a diverged cell started again from it; give it a flag
    that is not VALID there so that it does not also fuse). ``arrival``: each measurement in a push of its own with
    its map (the partner's frame second: the reference's push maps its motion measurement, the partner's push the
    stereo one, on the same frame). Returns the last map."""
    a = SimpleNamespace(seq=seq, stamp_us=seq * 66_667)
    st = r.states["nose"]
    res = None
    for j, flags in enumerate(flag_rows):
        inst = r._instant("nose", a) if r.config.n_per_instant else None
        if restart is not None and j == 0:
            sel = np.zeros(st.shape, bool)
            sel[:, restart] = True
            _start_cells(st, sel.ravel(), RHO, STD ** 2, UpdateConfig())
        args = meas(st.shape, flags)
        if j == len(flag_rows) - 1 or arrival:
            _, res = update_and_map(st, *args, UpdateConfig(), MAP, kernels=kernels)
        else:
            update(st, *args, kernels=kernels)
        if inst is not None:
            r._count_instant("nose", inst, res if j == len(flag_rows) - 1 or arrival else None)
    return res


V, L = VALID, LOW_TEXTURE


@pytest.mark.parametrize("kernels", PATHS)
def test_a_rig_frame_counts_once_and_its_unrepeated_cell_is_withdrawn(kernels):
    # columns: 0 both pairs of frame 1 range it, then LOW_TEXTURE (faint sky ranged by both pairs of one frame);
    # 1 ranged by both pairs of frames 1 and 2, then LOW_TEXTURE (repeated by a later frame); 2 only frame 1's motion
    # pair ranges it (the stereo pair LOW_TEXTURE: held already in frame 1's map, as before); 3 ranged by frame 1's
    # stereo pair only; 4 both pairs of every frame (n 1, 2, 3); 5 never ranged
    r, off = runner(True), runner(False)
    maps = {}
    for rr, key in ((r, "on"), (off, "off")):
        m1 = instant(rr, 1, [(V, V, V, L, V, L), (V, V, L, V, V, L)], kernels)
        m2 = instant(rr, 2, [(L, V, L, L, V, L), (L, V, L, L, V, L)], kernels)
        m3 = instant(rr, 3, [(L, L, L, L, V, L), (L, L, L, L, V, L)], kernels)
        maps[key] = (m1, m2, m3)
    st, st_off = r.states["nose"], off.states["nose"]
    assert st.n[0].tolist() == [1, 2, 1, 1, 3, 0]          # instants
    assert st_off.n[0].tolist() == [2, 4, 1, 1, 6, 0]      # measurements
    m1, m2, m3 = maps["on"]
    assert np.array_equal(m3.info["n_fused"], st.n)        # the map's n_fused is the state's
    assert m1.info["n_fused"][0].tolist() == [1, 1, 1, 1, 1, 0]
    # frame 1's map: the same with the rule on and off (fresh cells; column 2 held in both)
    o1, o2, o3 = maps["off"]
    assert np.array_equal(m1.flags, o1.flags) and np.array_equal(m1.range_m, o1.range_m, equal_nan=True)
    assert (m1.flags[:, 2] == ILL_CONDITIONED).all() and (m1.flags[:, [0, 1, 3, 4]] == VALID).all()
    # frame 2: column 0, one frame's look that frame 2 did not repeat, withdrawn; kept with measurements counted
    assert (m2.flags[:, 0] == ILL_CONDITIONED).all() and np.isnan(m2.range_m[:, 0]).all()
    assert (o2.flags[:, 0] == VALID).all() and np.allclose(o2.range_m[:, 0], 25.0, rtol=1e-4)
    assert (m2.flags[:, 3] == ILL_CONDITIONED).all() and (o2.flags[:, 3] == ILL_CONDITIONED).all()
    # frame 3: column 1 (two frames) still reported, column 4 fresh
    assert (m3.flags[:, 1] == VALID).all() and (m3.flags[:, 4] == VALID).all()
    assert (m3.flags[:, 0] == ILL_CONDITIONED).all() and (o3.flags[:, 0] == VALID).all()


@pytest.mark.parametrize("kernels", PATHS)
def test_a_cell_restarted_within_the_frame_counts_one_and_one_measurement_a_frame_is_unchanged(kernels):
    # a cell of 2 instants restarted by the frame's motion measurement (diverged), then fused by its stereo one: n 1
    # (the restart dropped its history: one look); a cell of 2 instants fused by both pairs: 3
    r = runner(True, cols=2)
    instant(r, 1, [(V, V), (V, V)], kernels)
    instant(r, 2, [(V, V), (V, V)], kernels)
    assert r.states["nose"].n[0].tolist() == [2, 2]
    instant(r, 3, [(L, V), (V, V)], kernels, restart=[0])
    assert r.states["nose"].n[0].tolist() == [1, 3]
    # one measurement a frame (one camera): n counts them as before, nothing capped
    one, off = runner(True, cols=2), runner(False, cols=2)
    for k in range(1, 4):
        m_on, m_off = instant(one, k, [(V, L)], kernels), instant(off, k, [(V, L)], kernels)
        assert np.array_equal(m_on.flags, m_off.flags) and np.array_equal(m_on.info["n_fused"], m_off.info["n_fused"])
    assert one.states["nose"].n[0].tolist() == [3, 0] and one.counts.get("n_instant_capped", 0) == 0


@pytest.mark.parametrize("kernels", PATHS)
def test_the_partner_frame_second_counts_the_frame_once_across_its_two_pushes(kernels):
    # --rig-order arrival: the reference's push fuses and maps its motion measurement, the partner's push its stereo
    # one, on the same reference frame: the same count as in one push, and the frame-1 look withdrawn in frame 2
    one, two = runner(True), runner(True)
    rows1 = [(V, V, V, L, V, L), (V, V, L, V, V, L)]
    rows2 = [(L, V, L, L, V, L), (L, V, L, L, V, L)]
    instant(one, 1, rows1, kernels)
    m1 = instant(two, 1, rows1, kernels, arrival=True)
    assert np.array_equal(m1.info["n_fused"], one.states["nose"].n)
    instant(one, 2, rows2, kernels)
    m2 = instant(two, 2, rows2, kernels, arrival=True)
    assert one.states["nose"].n[0].tolist() == two.states["nose"].n[0].tolist() == [1, 2, 1, 1, 2, 0]
    assert (m2.flags[:, 0] == ILL_CONDITIONED).all() and (m2.flags[:, 1] == VALID).all()
