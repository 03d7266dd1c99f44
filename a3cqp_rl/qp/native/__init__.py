"""The small-batch dual active set in C (`gi_qp.c`, built at install time), called through ctypes.

Why native: at B = 1 the numpy range-space Goldfarb-Idnani of `small_batch.py` spends its time in
call overhead, ~12 active-set steps × ~10 numpy/LAPACK calls at 0.5-3 µs each, while the
arithmetic of a whole controller-sized solve (n = 13, m = 30) is a few µs.  One C call per batch
does the same steps with the same decisions and certificate (see `gi_qp.c`); the numpy code stays
as the fallback (not built: no compiler at install time; `A3CQP_NATIVE_QP=0`) and as the reference in tests.
Measured on the shared 2-core box (controller-sized instance of bench/qp.py, B = 1):
`active_set_small` cold 259 → 38 µs (default instance), 471 → 41 µs (spread 0.35, 12 solves);
of the native call, ~2.5 µs is ctypes, ~5-15 µs the C code, the rest the array handling here.
The backward (`gi_qp_adjoint`: adjoint solve and closed-form gradients) replaces ~30 numpy calls
(~100 µs) the same way.  `solve_qp` at B = 1, medians of 3 bench runs: forward cold 348 → 163 µs
(default), 614 → 222 µs (heavy); forward+backward 654 → 434, 942 → 481 µs.

Build: setup.py at install time (flags in `a3cqp_rl.native_sources`); loading: `a3cqp_rl.native_build`.  A missing
or stale library logs one warning and `load()` returns None for the rest of the process.
"""

from __future__ import annotations

import ctypes
import logging
from pathlib import Path
from typing import Callable

import numpy as np

from a3cqp_rl.native_build import LazyLibrary, address

__all__ = ["load", "load_adjoint", "SOURCE", "CERTIFIED"]

SOURCE = Path(__file__).with_name("gi_qp.c")
CERTIFIED = 0
"""Status code of a certified instance (any other code: solve it on the numpy path)."""

_log = logging.getLogger(__name__)


def _bind(path: Path) -> tuple[Callable, Callable]:
    """ctypes bindings of gi_qp_solve and gi_qp_adjoint wrapped as functions of numpy arrays."""
    lib = ctypes.CDLL(str(path))
    fn, fn_adj = lib.gi_qp_solve, lib.gi_qp_adjoint
    i64, dbl, ptr = ctypes.c_int64, ctypes.c_double, ctypes.c_void_p
    fn.argtypes = [i64, i64, i64, i64, ptr, ptr, ptr, ptr, ptr, ptr, ptr, dbl, i64, ptr, ptr, ptr, ptr, ptr]
    fn_adj.argtypes = [i64, i64, i64, i64, *[ptr] * 15]
    fn.restype = fn_adj.restype = ctypes.c_int
    f64, i64v = np.float64, np.int64

    def solve(
        P: np.ndarray, q: np.ndarray, A: np.ndarray, b: np.ndarray, G: np.ndarray, h: np.ndarray,
        z0: np.ndarray | None, tol: float, max_steps: int,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Range-space G-I on a batch (shapes as `small_batch.active_set_small`); returns x, y, z, status, solves.

        Inputs are made float64 C-contiguous (a no-op for the usual arrays); x, y, z are valid
        where status == CERTIFIED (0)."""
        B, n = q.shape
        p, m = A.shape[1], G.shape[1]
        P, q, A, b, G, h = (np.ascontiguousarray(t, dtype=f64) for t in (P, q, A, b, G, h))
        if z0 is not None:
            z0 = np.ascontiguousarray(z0, dtype=f64)
        # One output buffer (one address to take): x | y | z | status | solves.
        out = np.empty(B * (n + p + m + 2))
        e1, e2, e3 = B * n, B * (n + p), B * (n + p + m)
        x, y, z = out[:e1].reshape(B, n), out[e1:e2].reshape(B, p), out[e2:e3].reshape(B, m)
        codes = out[e3:].view(i64v)
        o = address(out)
        fn(B, n, p, m, address(P), address(q), address(A), address(b), address(G), address(h), None if z0 is None else address(z0),
           tol, max_steps, o, o + 8 * e1, o + 8 * e2, o + 8 * e3, o + 8 * (e3 + B))
        return x, y, z, codes[:B], codes[B:]

    def adjoint(
        P: np.ndarray, A: np.ndarray, G: np.ndarray, h: np.ndarray, x: np.ndarray, y: np.ndarray, z: np.ndarray, gx: np.ndarray,
    ) -> tuple[np.ndarray, ...] | None:
        """Gradients (gP, gq, gA, gb, gG, gh) of Σ gx·x by the range-space adjoint (`gi_qp_adjoint`), or None.

        None when some instance's system is not accepted (the caller then uses its numpy adjoint)."""
        B, n = x.shape
        p, m = A.shape[1], G.shape[1]
        P, A, G, h, x, y, z, gx = (np.ascontiguousarray(t, dtype=f64) for t in (P, A, G, h, x, y, z, gx))
        sizes = (n * n, n, p * n, p, m * n, m)
        out = np.empty(B * (sum(sizes) + 1))
        o, offs = address(out), [0]
        for s_ in sizes:
            offs.append(offs[-1] + B * s_)
        status = out[offs[-1]:].view(i64v)
        fn_adj(B, n, p, m, address(P), address(A), address(G), address(h), address(x), address(y), address(z), address(gx),
               *(o + 8 * e for e in offs))
        if status[status.argmax()]:  # any instance not accepted
            return None
        shapes = ((B, n, n), (B, n), (B, p, n), (B, p), (B, m, n), (B, m))
        return tuple(out[offs[i] : offs[i + 1]].reshape(shapes[i]) for i in range(6))

    return solve, adjoint


def load() -> Callable | None:
    """The native batch solver, or None (disabled by A3CQP_NATIVE_QP=0, or not built / stale: one warning)."""
    fns = _library.get()
    return None if fns is None else fns[0]


def load_adjoint() -> Callable | None:
    """The native backward (adjoint and gradients), or None exactly when `load()` is None."""
    fns = _library.get()
    return None if fns is None else fns[1]


def _reset() -> None:
    """Forget the loaded routine (tests: re-read the environment on the next `load()`)."""
    _library.reset()


_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_QP", _bind, _log, "a3cqp_rl.qp: native QP routine", "the numpy path")
