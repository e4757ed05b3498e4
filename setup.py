"""Build of the two C extensions: the cooperative solves' kernels (shared/swarmnav/estimators/_kernels.c)
and the peer-state frame's checks (shared/swarmnav/wire/_frames.c); everything else is in
pyproject.toml. `make setup` builds them (pip install -e .)."""
from setuptools import Extension, setup

IEEE = ["-O3", "-fno-fast-math", "-ffp-contract=off"]  # the arithmetic Python and numpy do, bit for bit
setup(ext_modules=[Extension("swarmnav.estimators._kernels", ["shared/swarmnav/estimators/_kernels.c"], extra_compile_args=IEEE),
                   Extension("swarmnav.wire._frames", ["shared/swarmnav/wire/_frames.c"], extra_compile_args=IEEE)])
