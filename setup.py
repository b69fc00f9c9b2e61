"""The compiled part of the package; everything else is in pyproject.toml.

`escape_cli.core._kernels` (farthest point sampling, nearest neighbours) is optional:
where no C compiler is found the install goes on, and `core.sampling` and
`core.neighbours` use numpy and scipy instead, with the same result.
"""

import sys

from setuptools import Extension, setup

# No contraction into fused multiply-adds: the kernel must round exactly as numpy does.
FLAGS = [] if sys.platform == "win32" else ["-O2", "-ffp-contract=off", "-fno-fast-math"]

setup(ext_modules=[Extension("escape_cli.core._kernels", ["src/escape_cli/core/_kernels.c"],
                             extra_compile_args=FLAGS, optional=True)])
