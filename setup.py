"""The runtime path's per-sample loops in plain C, loaded through ctypes by agent/kernels.py (no
Python API). ``pip install -e .`` builds agent/_kernels<EXT_SUFFIX> in place. -ffp-contract=off: no
fused multiply-add, so results are the same on every target (and match the numba reference).
Everything else about the package is in pyproject.toml."""

from setuptools import Extension, setup

setup(ext_modules=[Extension("agent._kernels", ["agent/_kernels.c"], extra_compile_args=["-O2", "-ffp-contract=off"],
                             libraries=["m"])])
