"""Method registry and the one pipeline function ``locate`` that the CLI and the services call.

Every method is ``fn(view_a: View, view_b: View, **params) -> RangeResult`` with ranges on view a's grid.
Methods are imported lazily so that ``eonav --help`` stays instant.
"""
from __future__ import annotations

import importlib

from eonav import InputError
from eonav.geometry.camera import View
from eonav.ranging.rangemap import RangeResult

METHODS = {
    "dense": ("eonav.ranging.methods.dense", "locate_dense",
              "direct inverse-range method: epipolar search + coarse-to-fine re-linearised eq. (27) (default)"),
    "dense_lr": ("eonav.ranging.consistency", "locate_dense_lr",
                 "dense, checked left-right: also run b -> a, the pixels it contradicts flagged OCCLUDED"),
    "paper": ("eonav.ranging.methods.paper", "locate_paper",
              "the paper, faithfully: recursive estimators (36)-(42), closed form (28), eq. (7) test"),
    "dis": ("eonav.ranging.methods.flow_baseline", "locate_dis",
            "baseline: OpenCV DIS optical flow + triangulation with the known motion"),
    "sgbm": ("eonav.ranging.methods.flow_baseline", "locate_sgbm",
             "baseline for rectified stereo pairs only: OpenCV StereoSGBM"),
}
DEFAULT_METHOD = "dense"


def get_method(name: str):
    if name not in METHODS:
        raise InputError(f"unknown method {name!r}; expected one of {sorted(METHODS)}")
    mod, fn, _ = METHODS[name]
    return getattr(importlib.import_module(mod), fn)


def locate(view_a: View, view_b: View, method: str = DEFAULT_METHOD, **params) -> RangeResult:
    """Range to every pixel of view a from the pair (view a, view b) and their known poses."""
    return get_method(method)(view_a, view_b, **params)
