"""A control period's sensing in C (`native/sense.c`): PandaSim's read-out after mj_step1 and f_ext = J^{T†} τ_ext.

Why native: at 65 arms the numpy form of `PandaSim._observe_arrays` (joint state, B(q), h + g, F/T reading, the
environment wrench on the tool, the control site's Jacobian, J̇q̇ and twist) and of `wrench_from_joint_torques` is
~50 numpy calls of 1-20 µs per control period, ~200 µs, for a few thousand flops per arm: ~10 % of a peg-in-hole
evaluation. The C file computes the same quantities in another order (Cholesky where numpy solves by LU), so the
two agree to round-off, not bit for bit (tests/test_sense.py); the numpy path stays the reference.

`A3CQP_NATIVE_SENSE=0` switches it off; a library not built at install time, or older than its source, logs one
warning and the numpy path runs.
"""

from __future__ import annotations

import ctypes
import logging
import weakref
from pathlib import Path
from contextlib import AbstractContextManager
from typing import TYPE_CHECKING, Callable

import numpy as np

from a3cqp_rl.native_build import LazyLibrary, address

if TYPE_CHECKING:
    from a3cqp_rl.robot.sim import PandaSim

__all__ = ["observer", "wrench", "numpy_sensing", "SOURCE"]

SOURCE = Path(__file__).with_name("native") / "sense.c"

_log = logging.getLogger(__name__)
_DATA = ("qpos", "qvel", "qfrc_bias", "M", "sensordata", "site_xpos", "site_xmat", "subtree_com", "cacc", "cvel",
         "cdof", "cdof_dot")
_INDEX = ("qadr", "dadr", "m_idx", "ft_adr", "ft_site", "ft_body", "root_body", "cs", "cs_body")
_OUT = ("q", "qd", "bias", "mass", "ft", "f_env", "cs_pos", "cs_rot", "jt", "twist", "jdot_qdot")


class _Args(ctypes.Structure):
    """`sense_args` of sense.c (the same field order)."""

    _fields_ = [("n", ctypes.c_int64), *((f, ctypes.c_void_p) for f in (*_DATA, *_INDEX, "cs_mask", "origin",
                                                                        "tree_awake", "arm_tree", *_OUT)),
                ("tool_mass", ctypes.c_double)]


def _bind(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    lib.sense_observe.argtypes = [ctypes.c_void_p]
    lib.sense_observe.restype = None
    lib.sense_wrench.argtypes = [ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64,
                                 ctypes.c_int64, ctypes.c_void_p, ctypes.c_double, ctypes.c_void_p]
    lib.sense_wrench.restype = None
    return lib


_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_SENSE", _bind, _log, "a3cqp_rl.robot: native sensing",
                       "the numpy sensing")


def numpy_sensing() -> AbstractContextManager[None]:
    """Within the block new PandaSims and f_ext take the numpy sensing (e.g. the peer of a benchmark)."""
    return _library.off()


def _index(a: np.ndarray | None) -> np.ndarray | None:
    return None if a is None else np.ascontiguousarray(a, dtype=np.int64)


def observer(sim: PandaSim) -> Callable[[], None] | None:
    """A call that fills `sim`'s observe() arrays from its MjData after mj_step1 (what `_observe_arrays` computes
    after it), or None where the library is off or absent. The arrays it reads and writes stay where they are for
    the sim's life (MjData's buffers are allocated once), so their addresses are taken here, once."""
    lib = _library.get()
    if lib is None:
        return None
    d, kin = sim.data, sim._cs is not None
    keep = {name: getattr(d, name) for name in _DATA}
    keep.update(qadr=_index(sim._qadr), dadr=_index(sim._dadr), m_idx=_index(sim._m_idx), ft_adr=_index(sim._ft_adr),
                ft_site=_index(sim._ft_site), ft_body=_index(sim._ft_body), root_body=_index(sim._root_body),
                cs=_index(sim._cs) if kin else None, cs_body=_index(sim._cs_body) if kin else None,
                cs_mask=None if not kin or sim._cs_mask is None else np.ascontiguousarray(sim._cs_mask, np.float64),
                origin=np.ascontiguousarray(sim._origin, dtype=np.float64),
                tree_awake=d.tree_awake if d.tree_awake.dtype == np.int32 else None, arm_tree=_index(sim._arm_tree))
    keep.update(q=sim._q, qd=sim._qd, bias=sim._bias, mass=sim._mass, ft=sim._ft, f_env=sim._f_env,
                cs_pos=sim._cs_pos, cs_rot=sim._cs_rot, jt=sim._jt, twist=sim._twist, jdot_qdot=sim._jdot_qdot)
    for name in _OUT:
        if not keep[name].flags.c_contiguous or keep[name].dtype != np.float64:
            raise ValueError(f"PandaSim's {name} array must be C-contiguous float64 for the native sensing")
    args = _Args(n=sim.n, tool_mass=sim._tool_mass,
                 **{k: (None if v is None else address(v)) for k, v in keep.items()})
    fn, ref = lib.sense_observe, ctypes.byref(args)

    def observe() -> None:
        fn(ref)

    observe._keep = (keep, args)  # the arrays and the struct live as long as the call
    observe.owner = weakref.ref(sim)  # a copy of the sim (copy.deepcopy) has other arrays: it binds its own
    return observe


def wrench(tau: np.ndarray, jac: np.ndarray, mass: np.ndarray, damping: float) -> np.ndarray | None:
    """f_ext = Λ J B⁻¹ τ [B, 6] (N, N m) from τ_ext [B, 7], J [B, 6, 7] (any strides) and B(q) [B, 7, 7], float64;
    0 where τ = 0; None where the library is off or absent (the caller's numpy path then runs)."""
    lib = _library.get()
    n = tau.shape[0] if tau.ndim == 2 else -1
    if lib is None or tau.shape != (n, 7) or jac.shape != (n, 6, 7) or mass.shape != (n, 7, 7):
        return None  # (other shapes, e.g. broadcast batches: the numpy path broadcasts them or says why not)
    tau, mass = np.ascontiguousarray(tau, dtype=np.float64), np.ascontiguousarray(mass, dtype=np.float64)
    if jac.dtype != np.float64 or any(s % 8 for s in jac.strides):
        jac = np.ascontiguousarray(jac, dtype=np.float64)
    out = np.empty((n, 6))
    if n:
        s0, s1, s2 = (s // 8 for s in jac.strides)
        base = jac.__array_interface__["data"][0]
        lib.sense_wrench(n, address(tau), base, s0, s1, s2, address(mass), float(damping), address(out))
    return out
