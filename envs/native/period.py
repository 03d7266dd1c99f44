"""PandaEnv's per-control-period arithmetic around the read-out in C (`period.c`): the tail of `_measure` (the F/T
moment at the tool tip, f_ope, the handle's position) and the divergence and joint-limit checks.

Why native: at 65 arms the numpy form is ~30 numpy calls of 2-15 µs per control period (~120 µs of ~2.2 ms) for
~100 flops and comparisons per arm. The checks' comparisons are the same; the wrenches agree with the numpy path to
round-off (tests/test_period_native.py); the numpy path stays the reference.

`A3CQP_NATIVE_PERIOD=0` switches it off; a library not built at install time, or older than its source, logs one
warning and the numpy path runs.
"""

from __future__ import annotations

import ctypes
import logging
from contextlib import AbstractContextManager
from pathlib import Path

import numpy as np

from a3cqp_rl.native_build import LazyLibrary, address, contiguous

__all__ = ["NativePeriod", "native_period", "numpy_period", "SOURCE", "WHY"]

SOURCE = Path(__file__).with_name("period.c")
WHY = {1: "non-finite state", 2: "joint speed beyond limit", 3: "contact penetration"}
"""Why an arm newly diverged, by `period_checks`' code (0: it did not); the numpy checks log with the same codes."""

_log = logging.getLogger(__name__)
_p = ctypes.c_void_p


class _Args(ctypes.Structure):
    """`period_args` of period.c (the same field order)."""

    _fields_ = [("n", ctypes.c_int64), ("speed_factor", ctypes.c_double), ("penetration", ctypes.c_double),
                *((f, _p) for f in ("dq_max", "q_lo", "q_hi", "o_ft", "o_handle"))]


def _bind(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    lib.period_args_size.restype = ctypes.c_int64
    if lib.period_args_size() != ctypes.sizeof(_Args):
        raise RuntimeError("period_args in period.c and envs.native.period differ")
    lib.period_measure.argtypes = [_p] * 9
    lib.period_measure.restype = None
    lib.period_checks.argtypes = [_p] * 11
    lib.period_checks.restype = ctypes.c_int64
    return lib


_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_PERIOD", _bind, _log, "envs: the control period's arithmetic in C",
                       "the numpy control period")


def numpy_period() -> AbstractContextManager[None]:
    """Within the block new PandaEnvs take the numpy control period (e.g. the reference of a test)."""
    return _library.off()


class NativePeriod:
    """`period_measure` and `period_checks` of one env's constants: the datasheet's joint limits (rad, rad/s), the
    divergence bounds, and the F/T site and the handle from the tool tip (tool frame, m)."""

    def __init__(self, lib: ctypes.CDLL, n: int, dq_max: np.ndarray, q_lo: np.ndarray, q_hi: np.ndarray,
                 speed_factor: float, penetration: float, o_ft: np.ndarray, o_handle: np.ndarray) -> None:
        self._lib, self.n = lib, n
        self._keep = tuple(contiguous(a) for a in (dq_max, q_lo, q_hi, o_ft, o_handle))
        self._args = _Args(n, float(speed_factor), float(penetration), *(address(a) for a in self._keep))
        self._ref = ctypes.byref(self._args)
        self._bad = np.zeros(n, dtype=np.uint8)

    def measure(self, pos: np.ndarray, rot: np.ndarray, ft: np.ndarray, truth: np.ndarray | None, f_ext: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Moments of ft (and truth, when another array) [N, 6] moved from the F/T site to the tool tip in place;
        returns f_ope = f_ext − ft [N, 6], the handle from the tip [N, 3] and its position [N, 3] (world; pos
        [N, 3], rot [N, 3, 3] the tip's pose; all C-contiguous float64)."""
        n = self.n
        f_ope, r, hp = np.empty((n, 6)), np.empty((n, 3)), np.empty((n, 3))
        self._lib.period_measure(self._ref, address(pos), address(rot), address(ft),
                                 None if truth is None or truth is ft else address(truth), address(f_ext),
                                 address(f_ope), address(r), address(hp))
        return f_ope, r, hp

    def checks(self, q: np.ndarray, qd: np.ndarray, pen: np.ndarray, pen_max: np.ndarray, skip: np.ndarray,
               live: np.ndarray, excess: np.ndarray, joint: np.ndarray, speed: np.ndarray) -> np.ndarray | None:
        """The divergence checks (q, qd [N, 7]; penetration `pen` [N], m, kept in `pen_max`; arms `skip` [N] not
        checked) and, for arms `live`, the joint-limit records `excess`, `joint`, `speed` [N] in place. Returns the
        codes (WHY) of the arms newly diverged [N] (uint8), or None when none did."""
        bad = self._bad
        count = self._lib.period_checks(self._ref, address(q), address(qd), address(pen), address(pen_max),
                                        address(skip.view(np.uint8)), address(live.view(np.uint8)), address(excess),
                                        address(joint), address(speed), address(bad))
        return bad.copy() if count else None


def native_period(n: int, **constants) -> NativePeriod | None:  # noqa: ANN003
    """NativePeriod for `n` arms (the keyword arguments of its constructor), or None where the library is off or
    absent."""
    lib = _library.get()
    return None if lib is None else NativePeriod(lib, n, **constants)
