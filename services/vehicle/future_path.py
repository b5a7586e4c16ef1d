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

import functools

import numpy as np

from services.model.geometry import Polyline
from services.vehicle.profile import FloatArray, SpeedProfile

MIN_SPACING_M = 0.1
"""Minimum distance between consecutive future-path points [m] (paper §IV-B)."""


@functools.lru_cache(maxsize=8)
def _sample_offsets(horizon_s: float, n_points: int) -> FloatArray:
    """Uniform sample times after now [s], shared (read-only): one per config."""
    offsets = np.linspace(0.0, horizon_s, n_points)
    offsets.flags.writeable = False
    return offsets


def future_path_points(
    profile: SpeedProfile,
    route: Polyline,
    now: float,
    horizon_s: float,
    n_points: int,
) -> FloatArray:
    """Points (x, y, t) of the future path, shape (M, 3), M ≤ n_points."""
    t_samples = now + _sample_offsets(horizon_s, n_points)
    t_known, s_known = profile.t, profile.s
    finite = np.isfinite(t_known)
    if not finite.all():
        t_known, s_known = t_known[finite], s_known[finite]
    # positions at the sample times; past the last finite time the car holds (a stop) or the
    # profile ends (goal or look-ahead reached)
    s_at = np.interp(t_samples, t_known, s_known)
    if s_at.shape[0] < 2 or float((s_at[1:] - s_at[:-1]).min()) >= MIN_SPACING_M:
        s_sel, t_sel = s_at, t_samples
    else:
        # slow or stopping somewhere: drop points too close to the last one kept
        s_list: list[float] = s_at.tolist()
        keep = [0]
        last = s_list[0]
        for i in range(1, len(s_list)):
            if s_list[i] - last >= MIN_SPACING_M:
                last = s_list[i]
                keep.append(i)
        if keep[-1] != len(s_list) - 1:
            keep.append(len(s_list) - 1)  # the hold point at the horizon
        s_sel, t_sel = s_at[keep], t_samples[keep]
    xy = route.points_at(s_sel)
    out = np.empty((s_sel.shape[0], 3), dtype=np.float64)
    out[:, 0:2] = xy
    out[:, 2] = t_sel
    return out
