"""The future-path builder: trajectory → positions with pass times (paper eq. 1).

The profile already carries eq. (1) pass times (``SpeedProfile.t``). The future
path samples it at ``n_points`` uniform times over the horizon ``T_free``
(10 s), so a moving car (≥ 1.2 m/s) sends exactly ``n_points`` points. Points
closer than 0.1 m to the previous one are dropped (the paper's minimum
spacing), so a slow or stopping car sends fewer; a stop ends the path with
two points at the exact stop position, the second timed at the horizon ("a
stop holds the last point until the horizon"): the zero-length last segment is
how a receiver (the RSU's velocity manager) sees that the path ends at rest. Had
the last kept point stayed a few cm short of the stop, the path would read as a
crawl that goes on past its end (issue 12, cause 1).
"""

from __future__ import annotations

import functools

import numpy as np

from services.model.geometry import Polyline
from services.vehicle.profile import FloatArray, SpeedProfile

MIN_SPACING_M = 0.1
"""Minimum distance between consecutive future-path points [m] (paper §IV-B)."""

_AT_REST_M = 1e-3
"""The last two samples closer than this [m]: the car is at rest at the path's end."""


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
        n = len(s_list)
        if keep[-1] != n - 1:
            keep.append(n - 1)  # the hold point at the horizon
        s_sel, t_sel = s_at[keep], t_samples[keep]
        if len(keep) >= 3 and n >= 2 and s_list[-1] - s_list[-2] < _AT_REST_M:
            # at rest at the end: the last kept point moves (< MIN_SPACING_M) to the stop
            # itself, so the path ends with a zero-length segment (a held stop)
            s_sel = s_sel.copy()
            s_sel[-2] = s_sel[-1]
    xy = route.points_at(s_sel)
    out = np.empty((s_sel.shape[0], 3), dtype=np.float64)
    out[:, 0:2] = xy
    out[:, 2] = t_sel
    return out
