"""Types of a route's projection and the bodies' overlap test in C
(``services/model/_geometry.c``)."""

import numpy as np
import numpy.typing as npt

def project_many(
    a: npt.NDArray[np.float64],
    unit: npt.NDArray[np.float64],
    seglen: npt.NDArray[np.float64],
    cumlen: npt.NDArray[np.float64],
    p: npt.NDArray[np.float64],
    /,
) -> tuple[npt.NDArray[np.float64], npt.NDArray[np.float64]] | None: ...
def any_quads_overlap(a: npt.NDArray[np.float64], b: npt.NDArray[np.float64], /) -> bool | None: ...
