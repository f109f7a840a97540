"""Frames, rotations and cameras: the paper's transformations (eqs. 8-14, 24-26) and the pinhole camera on a body.

Pure numpy; every other layer builds on it. ``frames``: rotations T1 (camera <- body), T2 (body <- NED), quaternions,
relative pose of two views. ``camera``: the ``Camera`` model, ``VehicleState``, ``View`` and ``pair_geometry``.
"""
