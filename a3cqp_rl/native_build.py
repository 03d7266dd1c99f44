"""Find and load the package's C libraries, which setuptools compiles at install time (setup.py,
`a3cqp_rl.native_sources`).

Each C source `dir/name.c` is built by `pip install` into `dir/_name<extension suffix>` (in place for an editable
install).  Most are plain C called through ctypes (loaded with `ctypes.CDLL`, no Python state); the QP solver's
`_gi_qp` is also a CPython extension module, imported by `a3cqp_rl.qp.native` for its entry points.  Where a library is absent (no compiler at install time: setuptools
skips the optional extension with a warning), switched off by its environment variable, or older than its source
(edited after the build), the caller's pure-Python route runs after one warning naming the reason.
"""

from __future__ import annotations

import ctypes
import importlib.machinery
import logging
import os
import threading
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Callable, Generic, TypeVar

import numpy as np

__all__ = ["library_path", "enabled", "address", "contiguous", "LazyLibrary", "REBUILD_HINT"]

T = TypeVar("T")

REBUILD_HINT = ("rebuild with `pip install -e .` (or, in a source checkout, `python setup.py build_ext --inplace`) where a "
                "C compiler is available")


def library_path(source: Path) -> Path | None:
    """The compiled library of C file `source` (`_<stem>` plus this interpreter's extension suffix), or None."""
    for suffix in importlib.machinery.EXTENSION_SUFFIXES:
        candidate = source.with_name(f"_{source.stem}{suffix}")
        if candidate.is_file():
            return candidate
    return None


def enabled(var: str) -> bool:
    """False when the environment variable `var` switches the native code off (0, false, no, off)."""
    return os.environ.get(var, "1").strip().lower() not in ("0", "false", "no", "off")


def contiguous(a: np.ndarray, dtype: type = np.float64) -> np.ndarray:
    """`a` as a C-contiguous array of `dtype` (itself where it is one already), for a C argument."""
    return np.ascontiguousarray(a, dtype=dtype)


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


def _find(source: Path, depends: tuple[Path, ...] = ()) -> Path:
    """The built library of `source` (which includes the headers `depends`); RuntimeError saying why none is usable."""
    lib = library_path(source)
    if lib is None:
        raise RuntimeError(f"{source.name} was not compiled at install time; {REBUILD_HINT}")
    for part in (source, *depends):
        if part.is_file() and part.stat().st_mtime > lib.stat().st_mtime:
            # an edited source with the old library would run old code next to new Python bindings
            raise RuntimeError(f"{lib.name} is older than {part.name}; {REBUILD_HINT}")
    return lib


class LazyLibrary(Generic[T]):
    """A C library loaded and bound once per process, on first `get()`.

    `bind(path)` turns the library into what callers use (ctypes functions, wrappers). `get()` returns it, or None
    when the environment variable `switch` turns the native code off, or after one warning on `log` when the library
    is missing, stale (older than its source or a header in `depends`) or fails to bind (the caller then takes its
    `fallback` path).
    """

    def __init__(self, source: Path, switch: str, bind: Callable[[Path], T], log: logging.Logger, what: str,
                 fallback: str, depends: tuple[Path, ...] = ()) -> None:
        self.source, self.switch, self.bind, self.log, self.what, self.fallback = source, switch, bind, log, what, fallback
        self.depends = tuple(depends)
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
                        value = self.bind(_find(self.source, self.depends))
                    except Exception as exc:  # missing, stale, or a layout mismatch found by `bind`
                        self.log.warning("%s unavailable (%s); using %s", self.what, exc, self.fallback)
                self._state = (True, value)
        return self._state[1]

    def reset(self) -> None:
        """Forget the loaded library (tests: re-read the environment on the next `get()`)."""
        with self._lock:
            self._state = (False, None)

    @contextmanager
    def off(self) -> Iterator[None]:
        """Within the block `get()` returns None, so callers take their fallback (a benchmark's peer); the state
        before it comes back after."""
        with self._lock:
            saved, self._state = self._state, (True, None)
        try:
            yield
        finally:
            with self._lock:
                self._state = saved
