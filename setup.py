"""The optional C speed-ups of the codec (``protocol/_speedups.c``); all else is in
pyproject.toml. Here only because the extension needs numpy's headers, which the
declarative ``[tool.setuptools]`` tables cannot find. ``optional=True``: without a C
compiler the install still succeeds and ``protocol/codec.py`` uses its numpy path (same
bytes); ``make test`` on CI insists that it was built (``tests/protocol/test_speedups.py``).
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
        )
    ]
)
