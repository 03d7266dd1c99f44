"""The C libraries built at install time (setup.py, a3cqp_rl.native_sources) and how a3cqp_rl.native_build loads them."""

from __future__ import annotations

import ctypes
import logging
import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest

from a3cqp_rl.native_build import LazyLibrary, library_path
from a3cqp_rl.native_sources import NATIVE_SOURCES

ROOT = Path(__file__).resolve().parents[1]
CC = shutil.which("cc") or shutil.which("gcc")


@pytest.mark.skipif(CC is None, reason="no C compiler: the pure-Python routes are the intended ones here")
@pytest.mark.parametrize("source", sorted(NATIVE_SOURCES))
def test_every_library_is_built_where_a_compiler_exists(source: str) -> None:
    # Guards the skips of the native tests: with a compiler, an install that left a library out is a failure.
    path = ROOT / source
    lib = library_path(path)
    assert lib is not None, f"{source} has no compiled library next to it: run `pip install -e .`"
    assert lib.stat().st_mtime >= path.stat().st_mtime, f"{lib.name} is older than {source}: rebuild"


def test_every_c_source_is_listed_for_the_build() -> None:
    found = {str(p.relative_to(ROOT)) for p in ROOT.glob("**/native/*.c") if ".venv" not in p.parts}
    assert found == set(NATIVE_SOURCES)


def _lib_for(tmp_path: Path, bind_log: list) -> tuple[Path, LazyLibrary]:
    src = tmp_path / "answer.c"
    src.write_text("int answer(void) { return 42; }\n")
    lazy = LazyLibrary(src, "A3CQP_TEST_NATIVE", lambda p: bind_log.append(p) or ctypes.CDLL(str(p)),
                       logging.getLogger("test_native_build"), "test library", "the slow path")
    return src, lazy


@pytest.mark.skipif(CC is None, reason="needs a C compiler to make a library")
def test_lazy_library_loads_a_built_library_once(tmp_path: Path, monkeypatch) -> None:
    binds: list = []
    src, lazy = _lib_for(tmp_path, binds)
    out = tmp_path / "_answer.so"  # the plain suffix is one of EXTENSION_SUFFIXES
    subprocess.run([CC, "-shared", "-fPIC", "-o", str(out), str(src)], check=True)
    assert lazy.get().answer() == 42 and lazy.get().answer() == 42 and len(binds) == 1
    with lazy.off():  # a benchmark's peer: the fallback within the block, the library again after it
        assert lazy.get() is None
    assert lazy.get().answer() == 42 and len(binds) == 1
    monkeypatch.setenv("A3CQP_TEST_NATIVE", "0")
    lazy.reset()
    assert lazy.get() is None and len(binds) == 1


@pytest.mark.skipif(CC is None, reason="needs a C compiler to make a library")
def test_a_library_older_than_its_source_is_refused_with_one_warning(tmp_path: Path, caplog) -> None:
    src, lazy = _lib_for(tmp_path, [])
    out = tmp_path / "_answer.so"
    subprocess.run([CC, "-shared", "-fPIC", "-o", str(out), str(src)], check=True)
    later = time.time() + 10
    os.utime(src, (later, later))  # the source edited after the build
    with caplog.at_level(logging.WARNING, logger="test_native_build"):
        assert lazy.get() is None and lazy.get() is None
    assert len(caplog.records) == 1
    msg = caplog.records[0].getMessage()
    assert "older than answer.c" in msg and "pip install -e ." in msg and "the slow path" in msg


def test_a_missing_library_falls_back_with_one_warning(tmp_path: Path, caplog) -> None:
    _, lazy = _lib_for(tmp_path, [])
    with caplog.at_level(logging.WARNING, logger="test_native_build"):
        assert lazy.get() is None and lazy.get() is None
    assert len(caplog.records) == 1 and "not compiled at install time" in caplog.records[0].getMessage()
