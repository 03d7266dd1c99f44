"""An exact MuJoCo contact filter (C, `native/contact_filter.c`) that spares the narrow phase mesh-box pairs proven apart.

MuJoCo's default filter for a candidate geom pair is the contype/conaffinity test; after it, a bounding-sphere test and
(inside the narrow phase) oriented-box tests decide whether GJK runs. A peg (mesh) in a bore made of boxes passes those
against most of the bore's boxes at every step although it touches a few: 28 µs of collision per peg centred in the
bore without any contact, 9 µs with this filter (docs/panda.md, "Evaluation speed"). The filter repeats MuJoCo's
contype/conaffinity test and then, for a mesh against a box, drops the pair when the mesh's vertices projected on one
of the box's axes lie beyond its face by more than the pair's margin + gap + 10 µm: GJK would find no contact there, so
the contacts, their order and the simulation are the same bit for bit (tests/test_contact_filter.py).

MuJoCo's callback is one per process (`mjcb_contactfilter`), so `install()` sets it for every model of the process; it
is a no-op when another callback is already set, when `A3CQP_NATIVE_CONTACT_FILTER=0`, or when the library is missing
or was compiled against another MuJoCo version than the one loaded (it reads mjModel/mjData fields directly).
"""

from __future__ import annotations

import ctypes
import logging
from pathlib import Path

import mujoco

from a3cqp_rl.native_build import LazyLibrary

__all__ = ["install", "uninstall", "installed"]

logger = logging.getLogger(__name__)

_FILTER_T = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int)


def _mujoco_version_number() -> int:
    major, minor, patch = (int(x) for x in mujoco.__version__.split(".")[:3])
    return 1000000 * major + 1000 * minor + patch


def _bind(path: Path):  # noqa: ANN202
    lib = ctypes.CDLL(str(path))
    lib.a3cqp_contact_filter_version.restype = ctypes.c_int
    built, loaded = lib.a3cqp_contact_filter_version(), _mujoco_version_number()
    if built != loaded:
        raise RuntimeError(f"compiled against MuJoCo {built}, running {mujoco.__version__}")
    return _FILTER_T(ctypes.cast(lib.a3cqp_contact_filter, ctypes.c_void_p).value)


_LIB = LazyLibrary(Path(__file__).parent / "native" / "contact_filter.c", "A3CQP_NATIVE_CONTACT_FILTER", _bind, logger,
                   "the C contact filter", "MuJoCo's own filter (the same contacts, slower in the peg's bore)")


def installed() -> bool:
    """Whether this module's filter is MuJoCo's contact filter callback now."""
    fn = _LIB.get()
    cur = mujoco.get_mjcb_contactfilter()
    return fn is not None and cur is not None and ctypes.cast(cur, ctypes.c_void_p).value == ctypes.cast(
        fn, ctypes.c_void_p).value


def install() -> bool:
    """Set the filter as MuJoCo's contact filter callback (for every model of the process); True when it is set."""
    fn = _LIB.get()
    if fn is None:
        return False
    cur = mujoco.get_mjcb_contactfilter()
    if cur is None:
        mujoco.set_mjcb_contactfilter(fn)
        return True
    return installed()  # someone else's callback stays


def uninstall() -> None:
    """Back to MuJoCo's own filter (if this module's filter is the callback)."""
    if installed():
        mujoco.set_mjcb_contactfilter(None)
