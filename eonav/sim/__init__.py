"""Simulator with ground truth: ray-traced textured scenes (ground, runway, boxes, sky) rendered by any
``Camera`` at any ``VehicleState``.

- ``eonav.sim.render.render(scene, camera, state)`` -> ``Render`` (image, range_m, object_id)
- ``eonav.sim.presets.make_pair(name)`` / ``write_pair`` : named two-view scenes ("paper", "fast", ...)
- ``eonav.sim.flight.render_flight(name, n_frames=..., rate_hz=...)`` : continuous flights
- ``eonav sim PRESET --out DIR`` : the command line (``eonav.sim.command``)
Submodules are imported on demand (numpy, cv2 are loaded only when used).
"""
