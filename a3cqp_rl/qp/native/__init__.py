"""The C route of `solve_qp` (`gi_qp.c`: dense Goldfarb-Idnani per instance, and the vector-Jacobian product of its
solution, built at install time as a CPython extension module whose two functions take data addresses).

Why C: at the controller's size (n = 13, m = 30) a whole solve is a few µs of arithmetic, while any
interpreted loop pays ~1 µs per call (numpy) or ~5 µs per op (eager torch) many times per active-set
step.  One C call runs the whole batch: input checks, bound handling, the active set and its certificate.

`load()` returns a `NativeQP` with the module's two functions (`solver.py` calls them with tensor data pointers as
ints and its numpy buffers as the arrays themselves: taking an array's address in Python costs ~0.3 µs, of a B = 1
`solve_qp` of ~7; ctypes' own argument conversion measured no slower than the module's parsing) or None: when the library was not built (no C compiler at install
time) or is older than its source (one warning), or when the environment variable A3CQP_NATIVE_QP=0
switches the C code off; `solve_qp(backend="auto")` then takes the torch route and `backend="c"` raises.

Build: setup.py at install time (flags in `a3cqp_rl.native_sources`); loading: `a3cqp_rl.native_build`.
"""

from __future__ import annotations

import importlib.machinery
import importlib.util
import logging
from pathlib import Path
from typing import Callable, NamedTuple

from a3cqp_rl.native_build import LazyLibrary

__all__ = ["load", "NativeQP", "SOURCE", "HANDED_ON", "N_STRIDES"]

SOURCE = Path(__file__).with_name("gi_qp.c")
HANDED_ON = 16
"""Status codes ≥ this are instances the C route hands on to the torch route (P not definite, dependent
rows, infeasible or unbounded candidates, no certificate); below it they are `QPStatus` values."""
N_STRIDES = 9
"""Batch strides passed per call: P, q, A, b, G, h, lb, ub, z0 (0: one array shared by the batch)."""

_log = logging.getLogger(__name__)


class NativeQP(NamedTuple):
    """The C entry points (functions of the extension module taking sizes, data addresses as ints, and floats;
    `solver.py` calls them with tensor data pointers, no conversions)."""

    solve: Callable
    """gi_qp_solve(B, n, p, m, P, q, A, b, G, h, lb, ub, z0, strides, tol, max_steps, out) -> worst status."""
    vjp: Callable
    """gi_qp_vjp(B, n, p, m, P, A, G, h, lb, ub, solution buffer, gx, layout, out) -> worst adjoint status."""


def _bind(path: Path) -> NativeQP:
    """The extension module at `path` (a3cqp_rl.qp.native._gi_qp), imported from that file."""
    name = f"{__name__}._gi_qp"
    spec = importlib.util.spec_from_file_location(name, path, loader=importlib.machinery.ExtensionFileLoader(name, str(path)))
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return NativeQP(mod.solve, mod.vjp)


def load() -> NativeQP | None:
    """The C route, or None (switched off by A3CQP_NATIVE_QP=0, or no compiler / build failed: one warning)."""
    return _library.get()


def _reset() -> None:
    """Forget the loaded routine (tests: re-read the environment on the next `load()`)."""
    _library.reset()


_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_QP", _bind, _log, "a3cqp_rl.qp: native QP routine", "the torch route")
