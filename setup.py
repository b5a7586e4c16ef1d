"""The optional C speed-ups: of the codec (``protocol/_speedups.c``) and of the RSU's
reservation table query (``services/rsu/_scan.c``); all else is in pyproject.toml.
Here only because the extensions need numpy's headers, which the declarative
``[tool.setuptools]`` tables cannot find. ``optional=True``: without a C compiler the
install still succeeds and ``protocol/codec.py`` and ``services/rsu/reservation.py`` use
their numpy paths (same bytes, same conflicts); ``make test`` on CI insists that both were
built (``tests/protocol/test_speedups.py``, ``tests/rsu/test_scan.py``).
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
    ]
)
