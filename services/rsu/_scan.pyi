"""Types of the reservation table's C query and the path projections (``services/rsu/_scan.c``)."""

import numpy as np
import numpy.typing as npt

def scan(
    q: npt.NDArray[np.float64],
    hq: npt.NDArray[np.float64],
    dense: list[npt.NDArray[np.float64]],
    head: list[npt.NDArray[np.float64] | None],
    live: npt.NDArray[np.bool_],
    b_slot: npt.NDArray[np.int32],
    b_k: npt.NDArray[np.int64],
    b_start: npt.NDArray[np.int32],
    b_box: npt.NDArray[np.float32],
    rows: int,
    npts: npt.NDArray[np.int32],
    d_slot: npt.NDArray[np.float64],
    f_slot: npt.NDArray[np.float64],
    lat_slot: npt.NDArray[np.float64],
    rad_d: npt.NDArray[np.float64],
    rad_f: npt.NDArray[np.float64],
    params: tuple[float, float, float, float, float, float, float],
    out_time: npt.NDArray[np.float64],
    out_self: npt.NDArray[np.float64],
    out_other: npt.NDArray[np.float64],
    out_first: npt.NDArray[np.int64],
    /,
) -> int | None: ...
def segment_lengths(points: npt.NDArray[np.float64], /) -> npt.NDArray[np.float64] | None: ...
def farther_than(
    xy: npt.NDArray[np.float64], x: float, y: float, reach: float, /
) -> bool | None: ...
def project_many(
    xy: npt.NDArray[np.float64], q: npt.NDArray[np.float64], /
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64], npt.NDArray[np.int64]] | None: ...
def path_headings(points: npt.NDArray[np.float64], /) -> npt.NDArray[np.float64] | None: ...
def path_curvature(
    xy: npt.NDArray[np.float64], s: npt.NDArray[np.float64], base: float, /
) -> npt.NDArray[np.float64] | None: ...
def convex_contains(
    xy: npt.NDArray[np.float64],
    vertices: npt.NDArray[np.float64],
    edges: npt.NDArray[np.float64],
    tol: float,
    /,
) -> npt.NDArray[np.bool_] | None: ...
def within_bounds(
    points: npt.NDArray[np.float64], coord: float, t_max: float, /
) -> bool | None: ...
def gap_over(points: npt.NDArray[np.float64], max_dt: float, /) -> bool | None: ...
