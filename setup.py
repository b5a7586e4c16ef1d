"""The optional C speed-ups: of the codec (``protocol/_speedups.c``), of the RSU's
reservation table query and path projections (``services/rsu/_scan.c``) and of a route's
projection (``services/model/_geometry.c``); all else is in pyproject.toml.
Here only because the extensions need numpy's headers, which the declarative
``[tool.setuptools]`` tables cannot find. ``optional=True``: without a C compiler the
install still succeeds and ``protocol/codec.py``, ``services/rsu/`` and
``services/model/geometry.py`` use their numpy paths (same bytes, same numbers); ``make
test`` on CI insists that all three were built (``tests/protocol/test_speedups.py``,
``tests/rsu/test_scan.py``, ``tests/rsu/test_paths_kernel.py``,
``tests/model/test_geometry_kernel.py``).
"""

import numpy
from setuptools import Extension, setup

setup(
    ext_modules=[
        Extension(
            "protocol._speedups",
            ["protocol/_speedups.c"],
            include_dirs=[numpy.get_include()],
            # exact IEEE arithmetic: the C and numpy paths must give the same bits
            extra_compile_args=["-ffp-contract=off", "-fno-fast-math"],
            optional=True,
        ),
        Extension(
            "services.rsu._scan",
            ["services/rsu/_scan.c"],
            include_dirs=[numpy.get_include()],
            # the exact predicate's arithmetic as numpy's: no fused multiply-add
            extra_compile_args=["-ffp-contract=off", "-fno-fast-math"],
            optional=True,
        ),
        Extension(
            "services.model._geometry",
            ["services/model/_geometry.c"],
            include_dirs=[numpy.get_include()],
            extra_compile_args=["-ffp-contract=off", "-fno-fast-math"],
            optional=True,
        ),
    ]
)
