"""Ranging: a pair of views -> a range map with confidence (the paper's method and the dense method beyond it).

``locate`` is the pipeline function (pair -> ``RangeResult``); ``methods`` holds the estimators (``paper``, ``dense``
with its ``fill``, the ``flow_baseline`` of OpenCV optical flow); ``rangemap`` the result type and its flags;
``pair_policy`` judges which frames make a useful pair; ``scale_control`` picks the locate scale that keeps up.
Pure numpy / OpenCV / numba: no transport.
"""
