"""Build the package's C libraries (a3cqp_rl.native_build.NATIVE_SOURCES) at install time; metadata is in pyproject.toml.

The libraries are optional: without a C compiler the install succeeds with a warning and the pure-Python routes run.
"""

import importlib.util
from pathlib import Path

from setuptools import Extension, setup

_spec = importlib.util.spec_from_file_location("native_sources", Path(__file__).parent / "a3cqp_rl" / "native_sources.py")
_mod = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(_mod)


def mujoco_include() -> str | None:
    """The C headers shipped in the mujoco package of this environment (found without importing it), or None."""
    spec = importlib.util.find_spec("mujoco")
    if spec is None or not spec.submodule_search_locations:
        return None
    inc = Path(list(spec.submodule_search_locations)[0]) / "include"
    return str(inc) if (inc / "mujoco" / "mujoco.h").is_file() else None


def extension(source: str, flags: tuple[str, ...]) -> Extension | None:
    """A ctypes-loaded C library `dir/_stem.<suffix>` built from `dir/stem.c` (None: its MuJoCo headers are missing)."""
    path = Path(source)
    name = ".".join((*path.parent.parts, f"_{path.stem}"))
    headers = list(_mod.NATIVE_HEADERS.get(source, ()))
    include = sorted({str(Path(h).parent) for h in headers})
    if source in _mod.NATIVE_MUJOCO_HEADERS:
        mj = mujoco_include()
        if mj is None:
            print(f"warning: mujoco's C headers not found in the build environment; {source} is not built")
            return None
        include.append(mj)
    return Extension(name, [source], extra_compile_args=[*_mod.COMMON_FLAGS, *flags], libraries=["m"], optional=True,
                     include_dirs=include, depends=headers)


setup(ext_modules=[e for e in (extension(src, flags) for src, flags in _mod.NATIVE_SOURCES.items()) if e is not None])
