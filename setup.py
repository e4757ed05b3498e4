"""Build of the one C extension (the joint snapshot's normal equations, shared/swarmnav/estimators/
_kernels.c); everything else is in pyproject.toml. `make setup` builds it (pip install -e .)."""
from setuptools import Extension, setup

setup(ext_modules=[Extension("swarmnav.estimators._kernels", ["shared/swarmnav/estimators/_kernels.c"],
                             extra_compile_args=["-O3", "-fno-fast-math", "-ffp-contract=off"])])
