"""Compiles the firmware's C core into the package when the package is built.

Everything else about the package is declared in pyproject.toml; setuptools reads only the
extension from here. The core is built once, at install time, as `firmware_bridge._fw_core`, so
the car and the simulator never need a compiler at run time and nothing is ever written into
site-packages. The library carries the digest of the sources it came from: firmware_bridge.native
refuses a library that does not match the sources beside it (a checkout whose C was edited
without rebuilding: `make` or `python setup.py build_ext --inplace`).
"""

import importlib.util
import os

from setuptools import Extension, setup

_spec = importlib.util.spec_from_file_location(
    "core_sources",
    os.path.join(os.path.dirname(os.path.abspath(__file__)), "firmware_bridge", "core_sources.py"),
)
core_sources = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(core_sources)

root = os.path.dirname(os.path.abspath(__file__))

setup(
    ext_modules=[
        Extension(
            core_sources.LIBRARY_MODULE,
            sources=[os.path.relpath(str(p), root) for p in core_sources.SOURCES],
            depends=[os.path.relpath(str(p), root) for p in core_sources.HEADERS],
            include_dirs=[os.path.relpath(str(core_sources.CORE_SRC), root)],
            define_macros=[("CARRT_FW_SOURCE_DIGEST", f'"{core_sources.source_digest()}"')],
            extra_compile_args=[*core_sources.WARNING_FLAGS, "-O2"],
        )
    ]
)
