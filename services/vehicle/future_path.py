"""The future-path builder: trajectory → positions with pass times (paper eq. 1).

The profile already carries eq. (1) pass times (``SpeedProfile.t``). The future
path samples it at ``n_points`` uniform times over the horizon ``T_free``
(10 s), so a moving car (≥ 1.2 m/s) sends exactly ``n_points`` points. Points
closer than 0.1 m to the previous one are dropped (the paper's minimum
spacing), so a slow or stopping car sends fewer; a stop ends the path with
one point at the stop position timed at the horizon ("a stop holds the last
point until the horizon").
"""

from __future__ import annotations

import numpy as np

from services.vehicle.profile import FloatArray, SpeedProfile
from services.world.geometry import Polyline

MIN_SPACING_M = 0.1
"""Minimum distance between consecutive future-path points [m] (paper §IV-B)."""


def future_path_points(
    profile: SpeedProfile,
    route: Polyline,
    now: float,
    horizon_s: float,
    n_points: int,
) -> FloatArray:
    """Points (x, y, t) of the future path, shape (M, 3), M ≤ n_points."""
    t_samples = now + np.linspace(0.0, horizon_s, n_points)
    finite = np.isfinite(profile.t)
    t_known = profile.t[finite]
    s_known = profile.s[finite]
    # positions at the sample times; past the last finite time the car holds (a stop) or the
    # profile ends (goal or look-ahead reached)
    s_at = np.interp(t_samples, t_known, s_known)
    keep = np.ones(s_at.shape[0], dtype=bool)
    if not bool(np.all(np.diff(s_at) >= MIN_SPACING_M)):
        # slow or stopping somewhere: drop points too close to the last one kept
        last = s_at[0]
        for i in range(1, s_at.shape[0]):
            if s_at[i] - last >= MIN_SPACING_M:
                last = s_at[i]
            else:
                keep[i] = False
    keep[-1] = True  # the hold point at the horizon
    s_sel = s_at[keep]
    t_sel = t_samples[keep]
    xy = route.points_at(s_sel)
    out = np.empty((s_sel.shape[0], 3), dtype=np.float64)
    out[:, 0:2] = xy
    out[:, 2] = t_sel
    return out
