"""The planner's compiled core (planning/_lookahead.pyx); the rest of the build is in
pyproject.toml. Portable flags only: a wheel built on one x86_64 CPU must run on any other
(planning/_dense.h picks wider vector code when the module loads)."""

import importlib.util
from pathlib import Path

from Cython.Build import cythonize
from setuptools import Extension, setup

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("source_digest",
                                               HERE / "planning" / "source_digest.py")
_digest = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_digest)

core = Extension(
    "planning._lookahead",
    ["planning/_lookahead.pyx"],
    include_dirs=["planning"],
    libraries=["mvec"],  # glibc's vector math (planning/_vector_math.h)
    define_macros=[("PLANNING_SOURCE_DIGEST",
                    f'"{_digest.source_digest(HERE / "planning")}"')],
    extra_compile_args=["-O3"],
)

setup(ext_modules=cythonize([core], language_level=3))
