"""Build one of the package's C sources with the system compiler, once, into a per-user cache.

Shared by the native QP (`a3cqp_rl.qp.native`) and the native controller step (`a3cqp_rl.control.native`).
Compiler: `A3CQP_CC`, else `CC`, else `cc`/`gcc` on PATH; an explicit one that does not exist is an error (no
silent substitute).  Cache: `A3CQP_CACHE_DIR`, else `$XDG_CACHE_HOME/a3cqp_rl` or `~/.cache/a3cqp_rl`, one file
per hash of (source, compiler, flags, platform).  The library is written to a temporary file in that directory and
moved into place with `os.replace`, so concurrent processes (pytest-xdist workers, two trainers) never load half a
file; at worst both compile.
"""

from __future__ import annotations

import ctypes
import hashlib
import logging
import os
import platform
import shlex
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Callable, Generic, TypeVar

import numpy as np

__all__ = ["cache_dir", "compiler", "build", "enabled", "address", "LazyLibrary", "CFLAGS"]

T = TypeVar("T")

CFLAGS = ["-std=c99", "-O3", "-fPIC", "-shared"]
"""-O3: loop unswitching and vectorised axpy loops (the controller's QP at B = 64: 716 → 500 µs per batch against
-O2); IEEE semantics unchanged (no -ffast-math: reductions are not reassociated).  No -march=native: results must
not depend on the machine that built the library."""


def cache_dir() -> Path:
    """Directory of the compiled libraries."""
    env = os.environ.get("A3CQP_CACHE_DIR")
    if env:
        return Path(env)
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "a3cqp_rl"


def compiler() -> list[str] | None:
    """The compiler command (an explicit A3CQP_CC / CC may carry flags), or None when there is none."""
    for var in ("A3CQP_CC", "CC"):
        cmd = shlex.split(os.environ.get(var, ""))
        if cmd:
            exe = shutil.which(cmd[0])
            return [exe, *cmd[1:]] if exe else None
    exe = shutil.which("cc") or shutil.which("gcc")
    return [exe] if exe else None


def enabled(var: str) -> bool:
    """False when the environment variable `var` switches the native code off (0, false, no, off)."""
    return os.environ.get(var, "1").strip().lower() not in ("0", "false", "no", "off")


def build(source: Path, cflags: list[str] = CFLAGS, include_dirs: tuple[Path, ...] = ()) -> Path:
    """Path of the shared library compiled from `source`, compiling it if this source/compiler/flags is not cached.

    `include_dirs` go to the compiler as -I; their headers (*.h) are part of the cache key, so editing one rebuilds.
    Raises RuntimeError when there is no compiler or it fails (callers log one warning and use their numpy path).
    """
    cc = compiler()
    if cc is None:
        raise RuntimeError("no C compiler found (set A3CQP_CC or CC, or install cc/gcc)")
    src = source.read_bytes()
    includes = [f"-I{d}" for d in include_dirs]
    headers = [h.read_bytes() for d in include_dirs for h in sorted(Path(d).glob("*.h"))]
    key = hashlib.sha256(b"\0".join([src, *headers, " ".join(cc + cflags).encode(), platform.machine().encode(),
                                     sys.platform.encode()])).hexdigest()[:16]
    cache = cache_dir()
    lib = cache / f"{source.stem}-{key}.so"
    if lib.exists():
        return lib
    cache.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{source.stem}-", suffix=".so", dir=cache)
    os.close(fd)
    try:
        proc = subprocess.run([*cc, *cflags, *includes, "-o", tmp, str(source), "-lm"], capture_output=True, text=True,
                              timeout=120)
        if proc.returncode != 0:
            raise RuntimeError(f"{cc[0]} failed ({proc.returncode}): {proc.stderr.strip()[:500]}")
        os.replace(tmp, lib)  # atomic: readers see the old name absent or the whole file
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return lib


def address(a: np.ndarray) -> int:
    """Data address of a C-contiguous array, for a ctypes void* argument.

    ctypes' from_buffer takes ~0.5 µs where `a.ctypes.data` and `__array_interface__` take ~1.6 (a dict or object
    built per call), which for the several arrays of a call is most of a wrapper's cost at batch 1.
    """
    if a.size == 0:
        return 0  # never dereferenced (an empty block)
    try:
        return ctypes.addressof(ctypes.c_char.from_buffer(a))
    except TypeError:  # read-only array
        return a.__array_interface__["data"][0]


class LazyLibrary(Generic[T]):
    """A C source built, loaded and bound once per process, on first `get()`.

    `bind(path)` turns the compiled library into what callers use (ctypes functions, wrappers). `get()` returns it,
    or None when the environment variable `switch` turns the native code off, or after one warning on `log` when
    there is no compiler or the build or binding fails (the caller then takes its `fallback` path).
    """

    def __init__(self, source: Path, switch: str, bind: Callable[[Path], T], log: logging.Logger, what: str,
                 fallback: str, cflags: list[str] = CFLAGS, include_dirs: tuple[Path, ...] = ()) -> None:
        self.source, self.switch, self.bind, self.log, self.what, self.fallback = source, switch, bind, log, what, fallback
        self.cflags, self.include_dirs = cflags, tuple(include_dirs)
        self._lock = threading.Lock()
        self._state: tuple[bool, T | None] = (False, None)

    def get(self) -> T | None:
        """The bound library, or None (switched off, or unavailable: warned once)."""
        done, value = self._state  # (one tuple read: the hot path of every solve takes no lock)
        if done:
            return value
        with self._lock:
            if not self._state[0]:
                value = None
                if enabled(self.switch):
                    try:
                        value = self.bind(build(self.source, self.cflags, self.include_dirs))
                    except Exception as exc:  # no compiler, build error, unwritable cache, load error
                        self.log.warning("%s unavailable (%s); using %s", self.what, exc, self.fallback)
                self._state = (True, value)
        return self._state[1]

    def reset(self) -> None:
        """Forget the loaded library (tests: re-read the environment on the next `get()`)."""
        with self._lock:
            self._state = (False, None)
