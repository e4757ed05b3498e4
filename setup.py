"""Build of the one C extension (the joint snapshot's normal equations, shared/swarmnav/estimators/
_joint_kernel.c); everything else is in pyproject.toml. `make setup` builds it (pip install -e .)."""
from setuptools import Extension, setup

setup(ext_modules=[Extension("swarmnav.estimators._joint_kernel", ["shared/swarmnav/estimators/_joint_kernel.c"],
                             extra_compile_args=["-O2", "-fno-fast-math", "-ffp-contract=off"])])
