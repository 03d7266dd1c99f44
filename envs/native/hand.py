"""The operator's hand in C (`hand.c`): Operator.wrench and PandaSim.push of its wrench, one call per control period.

Why native: at 65 arms the numpy form is ~40 numpy calls of 2-30 µs per control period (~180 µs of ~2.2 ms) for a
few hundred flops per arm. The C file computes the same quantities with libm's atan2 and its own 3 × 3 products, so
the two agree to round-off, not bit for bit (tests/test_hand_native.py); the numpy path stays the reference.

`A3CQP_NATIVE_HAND=0` switches it off; a library not built at install time, or older than its source, logs one
warning and the numpy path runs.
"""

from __future__ import annotations

import ctypes
import logging
from contextlib import AbstractContextManager
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from a3cqp_rl.native_build import LazyLibrary, address, contiguous

if TYPE_CHECKING:
    from a3cqp_rl.robot.sim import PandaSim
    from envs.scenarios import Operator

__all__ = ["NativeHand", "native_hand", "numpy_hand", "SOURCE"]

SOURCE = Path(__file__).with_name("hand.c")

_log = logging.getLogger(__name__)
_d, _p = ctypes.c_double, ctypes.c_void_p
_CONFIG = ("stiffness", "damping", "intrinsic_damping", "rot_stiffness", "rot_damping", "speed", "grip_time",
           "max_force", "max_torque", "noise")


class _HandArgs(ctypes.Structure):
    """`hand_args` of hand.c (the same field order)."""

    _fields_ = [("n", ctypes.c_int64), ("lag", ctypes.c_int64), *((f, _d) for f in _CONFIG),
                *((f, _p) for f in ("state", "t_grasp", "t_release", "start", "goal", "rot_grasp", "force_scale",
                                    "primed", "hist"))]


class _PushArgs(ctypes.Structure):
    """`push_args` of hand.c (the same field order)."""

    _fields_ = [("n", ctypes.c_int64), *((f, _p) for f in ("site_xpos", "xipos", "subtree_com", "cdof",
                                                           "xfrc_applied", "site", "body", "root", "dadr", "mask",
                                                           "tau_push"))]


def _bind(path: Path) -> ctypes.CDLL:
    lib = ctypes.CDLL(str(path))
    for name, struct in (("hand_args_size", _HandArgs), ("push_args_size", _PushArgs)):
        fn = getattr(lib, name)
        fn.restype = ctypes.c_int64
        if fn() != ctypes.sizeof(struct):
            raise RuntimeError(f"{name[:-5]} in hand.c and envs.native.hand differ")
    lib.hand_wrench.argtypes = [_p, ctypes.c_int64, _p, _d, _p, _p, _p, _p, _p, ctypes.c_int64, _p, _p]
    lib.hand_wrench.restype = None
    lib.hand_push.argtypes = [_p, _p, _p]
    lib.hand_push.restype = ctypes.c_int64
    return lib


_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_HAND", _bind, _log, "envs: the operator's hand in C", "the numpy hand")


def numpy_hand() -> AbstractContextManager[None]:
    """Within the block new PandaEnvs take the numpy hand (e.g. the reference of a test)."""
    return _library.off()


class NativeHand:
    """Operator.wrench and PandaSim.push in C for one operator and its sim (addresses taken once: the operator's
    and MjData's arrays are written in place for their lives)."""

    def __init__(self, lib: ctypes.CDLL, operator: Operator, sim: PandaSim | None) -> None:
        op, c = operator, operator.cfg
        for name in ("state", "t_grasp", "t_release", "start", "goal", "rot_grasp", "force_scale", "_primed", "_hist"):
            a = getattr(op, name)
            if not a.flags.c_contiguous or a.dtype.itemsize != 8 and a.dtype != np.bool_:
                raise ValueError(f"Operator.{name} must be a C-contiguous 8-byte (or bool) array for the native hand")
        self._op, self._lib = op, lib
        self._args = _HandArgs(n=op.n, lag=op._lag, **{f: float(getattr(c, f)) for f in _CONFIG},
                               state=address(op.state), t_grasp=address(op.t_grasp), t_release=address(op.t_release),
                               start=address(op.start), goal=address(op.goal), rot_grasp=address(op.rot_grasp),
                               force_scale=address(op.force_scale), primed=address(op._primed.view(np.uint8)),
                               hist=address(op._hist))
        self._push = None
        if sim is not None:  # (a ShardedPandaSim pushes with its parts' own push)
            sid = sim._site_index("handle")
            body = sim.model.site_bodyid[sid]
            mask = sim._ancestor_mask(int(body[0]))
            d = sim.data
            self._keep = (d, *(contiguous(a, np.int64) for a in (sid, body, sim.model.body_rootid[body], sim._dadr)),
                          None if mask is None else contiguous(mask))
            _, s, b, r, dadr, m = self._keep
            self._sim = sim
            self._push = _PushArgs(n=sim.n, site_xpos=address(d.site_xpos), xipos=address(d.xipos),
                                   subtree_com=address(d.subtree_com), cdof=address(d.cdof),
                                   xfrc_applied=address(d.xfrc_applied), site=address(s), body=address(b),
                                   root=address(r), dadr=address(dadr), mask=None if m is None else address(m),
                                   tau_push=address(sim._tau_push))
        self._hand_ref, self._push_ref = ctypes.byref(self._args), (None if self._push is None
                                                                     else ctypes.byref(self._push))

    @property
    def pushes(self) -> bool:
        """Whether `__call__` also pushes the sim (else the caller pushes `force`, `torque`)."""
        return self._push is not None

    def __call__(self, t: np.ndarray, t_add: float, pos: np.ndarray, twist: np.ndarray, r: np.ndarray,
                 rot: np.ndarray, noise: np.ndarray | None, k_noise: int, force: np.ndarray, torque: np.ndarray) -> bool:
        """Operator.wrench at time `t` + `t_add` [N] (s) into `force`, `torque` [N, 3] (world) from the handle's
        position `pos` [N, 3], the tip's `twist` [N, 6], the handle from the tip `r` [N, 3] and `rot` [N, 3, 3]
        (all C-contiguous float64), the tremor draws noise[:, k_noise] ([N, K, 3], None: none); then, with a sim,
        its push. Returns whether any hand pushes."""
        op = self._op
        k = op._k
        op._k = (k + 1) % op._lag
        if noise is None:
            nz, stride = None, 0
        else:
            nz, stride = address(noise) + 8 * 3 * k_noise, 3 * noise.shape[1]
        self._lib.hand_wrench(self._hand_ref, k, address(t), t_add, address(pos), address(twist), address(r),
                              address(rot), nz, stride, address(force), address(torque))
        if self._push is None:
            return bool(force.any() or torque.any())
        return self.push(force, torque)

    def push(self, force: np.ndarray, torque: np.ndarray) -> bool:
        """PandaSim.push(force, site="handle", torque_world=torque) of C-contiguous float64 [N, 3] (world); returns
        whether any arm is pushed."""
        if self._lib.hand_push(self._push_ref, address(force), address(torque)):
            self._sim._pushed = True
            return True
        return False


def native_hand(operator: Operator, sim: PandaSim | None) -> NativeHand | None:
    """NativeHand of `operator` (pushing `sim`, a PandaSim; None: the caller pushes), or None where the library is
    off or absent."""
    lib = _library.get()
    return None if lib is None else NativeHand(lib, operator, sim)
