"""Types of a route's projection in C (``services/model/_polyline.c``)."""

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
