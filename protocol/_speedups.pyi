"""Types of the C speed-ups of the codec (``protocol/_speedups.c``)."""

from typing import Any

import numpy as np
import numpy.typing as npt

def pack(
    points: npt.NDArray[np.float64], t_base_ms: int, max_coord_cm: float, /
) -> tuple[int, bytes] | None: ...
def vehicle_path(
    points: npt.NDArray[np.float64],
    t_base_ms: int,
    max_coord_cm: float,
    x: float,
    y: float,
    speed: float,
    heading: float,
    length: float,
    width: float,
    /,
) -> tuple[int, int, int, int, int, int, int, bytes] | None: ...
def unpack(
    buf: bytes, off: int, n: int, widths: int, t_base_ms: int, max_coord_cm: float, /
) -> tuple[npt.NDArray[np.float64], int] | None: ...
def build(spec: tuple[type, tuple[Any, ...]], /, *values: Any) -> Any: ...
