"""Fusion over the stream: a recursive per-pixel inverse-range filter on the newest frame's grid.

One pair holds too little information where parallax is small; a camera delivers many frames a second. Each camera
keeps an ``InverseRangeState`` on the grid of its newest frame (inverse range rho = 1/x_c, its variance, a Beta
inlier evidence (a, b), the number of measurements fused and the sub-pixel position of the point each cell holds).
For every new frame:

1. ``predict``  -- carry the state into the new frame with the known relative pose: forward warp of every cell's
   point with a z-buffer (the nearest point wins where several land on one pixel), one-pixel cracks closed where
   their two opposite neighbours agree, holes start fresh; the variance grows with the Jacobian of the transfer
   and with process noise growing with time and motion;
2. ``measure``  -- a dense range map of the new frame against a partner chosen for parallax (``schedule``: the
   newest frame with enough parallax, as the pair policy judges it, alternating with the widest acceptable
   keyframe so that far points get a baseline; a stereo partner at the same instant too);
3. ``update``   -- each measured pixel fused into its cell under the Gaussian x uniform model with a Beta inlier
   ratio (Vogiatzis & Hernandez 2011, as REMODE, Pizzoli et al. 2014, and SVO's depth filter use it): an outlier
   leaves a converged cell where it was and lowers its inlier evidence; a cell whose evidence turns against it
   restarts from the measurement; pixels one pair cannot range only for their sigma (far, near the focus of
   expansion) are fused too: their measurements add up;
4. ``fused_map`` -- the state as a range map (the arrays of ``eonav locate``): only cells whose evidence agrees and
   whose sigma is tight are VALID; the rest is filled from them (FILLED) like a single pair's holes. Its sigma
   adds the error every pair shares (the window's slant error) to the filter's own.

``FusionRunner`` (``eonav.fusion.sequence``) runs the four stages over a stream of posed frames, one ``push`` per
frame: the code path of ``eonav fuse``, ``eonav bench fuse`` and the locator service alike. Pure: numpy, OpenCV and
the range methods; no transport.
"""
