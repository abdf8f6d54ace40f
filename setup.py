"""The compiled core (planning/_lookahead.pyx, the lookahead; planning/_routes.pyx, the route
fields; planning/_regression.pyx, the networks' training steps; planning/_evidence.pyx, the sums
of the cloud's jammer search; planning/_measuring.pyx, a UAV's report features and spot
filter; shared/_radio.pyx, the GBSs' received powers); the rest of the build is in
pyproject.toml. Portable flags only: a wheel built on one x86_64 CPU must run on any other
(planning/_dense.h and shared/_vector_math.h pick wider vector code when the module loads)."""

import importlib.util
import os
from pathlib import Path

from Cython.Build import cythonize
from setuptools import Extension, setup

HERE = Path(__file__).resolve().parent
_spec = importlib.util.spec_from_file_location("source_digest",
                                               HERE / "shared" / "source_digest.py")
_digest = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_digest)


def compiled(name: str, **options) -> Extension:
    """The module ``name`` (``planning._routes``) from its .pyx, stamped with the digest of
    every compiled source: a change to any of them makes every module stale, and so each is
    rebuilt."""
    return Extension(
        name,
        [name.replace(".", "/") + ".pyx"],
        include_dirs=["planning", "shared"],
        depends=list(_digest.COMPILED_SOURCES),
        define_macros=[("COMPILED_SOURCE_DIGEST", f'"{_digest.source_digest(HERE)}"')],
        extra_compile_args=["-O3"],
        **options,
    )


# The modules are translated and compiled on every core: the C compiler's work is most of an
# install's time.
CORES = os.cpu_count() or 1

setup(ext_modules=cythonize([
    compiled("planning._lookahead", libraries=["mvec"]),  # glibc's vector math
    compiled("planning._routes"),
    compiled("planning._regression"),
    compiled("planning._evidence", libraries=["mvec"]),
    compiled("planning._measuring"),
    compiled("shared._radio", libraries=["mvec"]),
], language_level=3, nthreads=CORES), options={"build_ext": {"parallel": CORES}})
