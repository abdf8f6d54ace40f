"""The compiled core (planning/_lookahead.pyx, the lookahead; planning/_routes.pyx, the route
fields; planning/_regression.pyx, the networks' training steps; planning/_evidence.pyx, the sums
of the cloud's jammer search; planning/_measuring.pyx, a UAV's report features and spot
filter); the rest of the build is in pyproject.toml. Portable flags only:
a wheel built on one x86_64 CPU must run on any other (planning/_dense.h picks wider vector code
when the module loads)."""

import importlib.util
from pathlib import Path

from Cython.Build import cythonize
from setuptools import Extension, setup

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("source_digest",
                                               HERE / "planning" / "source_digest.py")
_digest = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_digest)


def compiled(name: str, **options) -> Extension:
    """planning.<name> from planning/<name>.pyx, stamped with the digest of every compiled
    source: a change to any of them makes every module stale, and so each is rebuilt."""
    return Extension(
        f"planning.{name}",
        [f"planning/{name}.pyx"],
        include_dirs=["planning"],
        depends=[f"planning/{source}" for source in _digest.COMPILED_SOURCES],
        define_macros=[("PLANNING_SOURCE_DIGEST",
                        f'"{_digest.source_digest(HERE / "planning")}"')],
        extra_compile_args=["-O3"],
        **options,
    )


setup(ext_modules=cythonize([
    compiled("_lookahead", libraries=["mvec"]),  # glibc's vector math (planning/_vector_math.h)
    compiled("_routes"),
    compiled("_regression"),
    compiled("_evidence"),
    compiled("_measuring"),
], language_level=3))
