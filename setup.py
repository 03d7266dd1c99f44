"""Build the package's C libraries (a3cqp_rl.native_build.NATIVE_SOURCES) at install time; metadata is in pyproject.toml.

The libraries are optional: without a C compiler the install succeeds with a warning and the pure-Python routes run.
"""

import importlib.util
from pathlib import Path

from setuptools import Extension, setup

_spec = importlib.util.spec_from_file_location("native_sources", Path(__file__).parent / "a3cqp_rl" / "native_sources.py")
_mod = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_mod)


def extension(source: str, flags: tuple[str, ...]) -> Extension:
    """A ctypes-loaded C library `dir/_stem.<suffix>` built from `dir/stem.c`."""
    path = Path(source)
    name = ".".join((*path.parent.parts, f"_{path.stem}"))
    headers = list(_mod.NATIVE_HEADERS.get(source, ()))
    return Extension(name, [source], extra_compile_args=[*_mod.COMMON_FLAGS, *flags], libraries=["m"], optional=True,
                     include_dirs=sorted({str(Path(h).parent) for h in headers}), depends=headers)


setup(ext_modules=[extension(src, flags) for src, flags in _mod.NATIVE_SOURCES.items()])
