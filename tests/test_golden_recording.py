"""The golden recording (tests/data, made by ``python -m eonav.app.golden``): its inputs replayed through the real
sync, locator and obstacle services over a real zenoh bus reproduce the committed range maps and obstacle lists within
``eonav.app.golden.TOLERANCES``; and the comparison fails on outputs that drifted by more than those."""
from __future__ import annotations

import copy
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("zenoh")

from mcap.reader import make_reader  # noqa: E402

from eonav.bus import keys as K  # noqa: E402
from eonav.app import golden  # noqa: E402

DATA = Path(__file__).parent / "data"


def test_golden_inputs_are_what_the_docs_say():
    with open(DATA / golden.INPUTS, "rb") as f:
        reader = make_reader(f)
        s = reader.get_summary()
        counts = {s.channels[c].topic: n for c, n in s.statistics.channel_message_counts.items()}
        assert [a.name for a in reader.iter_attachments()] == [golden.CAMERAS_ATTACHMENT]
    assert counts[K.frame(golden.VEHICLE, "nose")] == golden.FLIGHT["n_frames"]
    assert counts[K.nav_state(golden.VEHICLE)] > 400                  # 50 + 25 + 25 + 25 Hz over ~5.4 s
    assert counts["/camera/nose/image"] == golden.FLIGHT["n_frames"]   # and it opens in Foxglove with pictures
    assert (DATA / golden.INPUTS).stat().st_size + (DATA / golden.EXPECTED_NPZ).stat().st_size < 3_000_000


@pytest.mark.pipeline
def test_golden_replay_reproduces_the_committed_outputs(tmp_path):
    out = golden.run_services(DATA / golden.INPUTS, tmp_path)
    assert out["exit_codes"] == {"replay": 0, "sync": 0, "locator": 0, "obstacles": 0}, out["exit_codes"]
    rep = golden.compare(out, golden.load_expected(DATA))
    print("worst differences:", golden.worst(rep))
    assert rep["ok"], rep["problems"]
    assert len(rep["maps"]) == 11 and len(rep["obstacles"]) > 50


def expected_as_outputs(exp: dict) -> dict:
    """The expected files as if a run had produced them (what compare takes)."""
    maps = [{"stamp_us": int(s), "other_stamp_us": int(o), "range_m": r, "flags": f}
            for s, o, r, f in zip(exp["stamp_us"], exp["other_stamp_us"], exp["range_m"], exp["flags"])]
    return {"range_maps": maps, "obstacle_lists": copy.deepcopy(exp["obstacle_lists"])}


def test_compare_fails_on_drift_beyond_the_tolerances():
    exp = golden.load_expected(DATA)
    assert golden.compare(expected_as_outputs(exp), exp)["ok"]

    def scaled(k):
        o = expected_as_outputs(exp)
        for m in o["range_maps"]:
            m["range_m"] = m["range_m"] * np.float32(k)
        return golden.compare(o, exp)
    assert scaled(1.0001)["ok"]                                   # 0.01 % longer: within median_rel 0.02 %
    bad = scaled(1.003)                                           # 0.3 % longer: drift
    assert not bad["ok"] and any("median_rel" in p for p in bad["problems"])

    o = expected_as_outputs(exp)                                  # 2 % of one map's pixels lose VALID
    f = o["range_maps"][4]["flags"].copy()
    valid = np.flatnonzero(f & 1)
    f.flat[valid[: int(0.02 * f.size)]] &= ~np.uint8(1)
    o["range_maps"][4]["flags"] = f
    assert any("valid_mismatch" in p for p in golden.compare(o, exp)["problems"])

    o = expected_as_outputs(exp)                                  # a map paired with another partner
    o["range_maps"][3]["other_stamp_us"] += 200_000
    assert any("pairs differ" in p for p in golden.compare(o, exp)["problems"])

    o = expected_as_outputs(exp)                                  # an obstacle lost, one moved by 1 %
    o["obstacle_lists"][2]["obstacles"].pop()
    o["obstacle_lists"][5]["obstacles"][0]["distance_m"] *= 1.01
    probs = golden.compare(o, exp)["problems"]
    assert any("obstacles, expected" in p for p in probs) and any("distance_rel" in p for p in probs)
    o = expected_as_outputs(exp)                                  # moved by 0.2 %: within distance_rel 0.5 %
    o["obstacle_lists"][5]["obstacles"][0]["distance_m"] *= 1.002
    assert golden.compare(o, exp)["ok"]


def test_compare_takes_a_runs_obstacles_in_any_order():
    """Obstacles are compared nearest first (golden.TOLERANCES): the comparison sorts a run's list itself, as the
    expected file is sorted, rather than relying on the obstacle service's order (nearest first today,
    eonav.obstacles.detect), so every list reversed still compares equal."""
    exp = golden.load_expected(DATA)
    o = expected_as_outputs(exp)
    for ol in o["obstacle_lists"]:
        ol["obstacles"].reverse()
    assert sum(len(ol["obstacles"]) > 1 for ol in o["obstacle_lists"]) == len(o["obstacle_lists"])
    rep = golden.compare(o, exp)
    assert rep["ok"], rep["problems"]


def test_compare_fails_on_an_obstacle_list_nobody_expected():
    """An obstacle list at a stamp with no expected one (a map made that should not have been) is a difference."""
    exp = golden.load_expected(DATA)
    o = expected_as_outputs(exp)
    last = o["obstacle_lists"][-1]
    o["obstacle_lists"].append(dict(copy.deepcopy(last), stamp_us=last["stamp_us"] + 200_000))
    rep = golden.compare(o, exp)
    assert not rep["ok"] and rep["problems"] == [f"unexpected obstacle lists at [{last['stamp_us'] + 200_000}]"]
