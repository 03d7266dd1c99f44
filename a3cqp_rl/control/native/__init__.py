"""The controller's default step in C (`a3cqp_step.c`): QP assembly and torque law (built at install time),
via ctypes.

Why native: on the CPU a control step of the Python objects is a few hundred numpy calls on 6×7 / 7×7 matrices at
0.5-3 µs each (and 10-25 µs each for 64 stacked matrices), while its arithmetic is ~20 k flops per arm.  The C file
is a line-by-line translation of the default composition (CartesianIK, Admittance, ForceControl, JointCentering,
the Cartesian regularizer; JointLimitsViability, WrenchBox, FrictionPyramid, TorqueLimits; eq. 4-7), so that
`A3CQPController` takes it when its tasks and limits are exactly those and the step runs on CPU float64; any other
composition (a custom task or limit, other devices, autograd through `build_context`) runs the Python objects, which
stay the reference (tests/test_control_native.py: agreement to 1e-9).  The QP itself is still `solve_qp`.

`A3CQP_NATIVE_CONTROL=0` switches it off; a library not built at install time (no compiler) or stale logs one warning and the Python path runs.
"""

from __future__ import annotations

import ctypes
import logging
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from a3cqp_rl.native_build import LazyLibrary, address

if TYPE_CHECKING:
    from a3cqp_rl.control.controller import A3CQPController

__all__ = ["Params", "NativeStep", "Assembled", "load", "native_params", "SOURCE", "INPUTS"]

SOURCE = Path(__file__).with_name("a3cqp_step.c")

_log = logging.getLogger(__name__)

_d = ctypes.c_double


class Params(ctypes.Structure):
    """`a3cqp_params` of a3cqp_step.c, field by field (flags are 0.0 / 1.0); see the C file for the meaning."""

    _fields_ = [("dt", _d), ("cv", _d), ("cp", _d), ("kp", _d * 6), ("kv", _d * 6),
                ("lambda_d", _d), ("c_d", _d), ("ac_paper", _d), ("f_d_max", _d), ("wrench_ff", _d), ("pd_pinv", _d),
                ("creg_gamma", _d), ("q_center", _d * 7), ("kq", _d), ("jc_eps", _d), ("jc_eps_n", _d),
                ("reg", _d), ("pinv_damping", _d), ("nullspace_damping", _d),
                ("q_min", _d * 7), ("q_max", _d * 7), ("dq_max", _d * 7), ("ddq_max", _d * 7),
                ("horizon", _d), ("target_total", _d), ("include_f_ext", _d), ("brake_gain", _d),
                ("has_tau_stop", _d), ("tau_stop_max", _d * 7), ("torque_share", _d), ("min_stop_fraction", _d),
                ("wrench_max", _d * 6), ("mu", _d),
                ("has_torque_limits", _d), ("torque_max", _d * 7), ("torque_safe", _d),
                ("tau_clip", _d * 7), ("leak", _d)]


def _vec(values, n: int):  # noqa: ANN001, ANN202
    return (_d * n)(*[float(v) for v in np.asarray(values, dtype=np.float64).reshape(n)])


def native_params(ctrl: A3CQPController) -> tuple[Params | None, str]:
    """The C parameters of `ctrl`, or (None, why) when its tasks/limits are not the default composition."""
    from a3cqp_rl.control.limits import FrictionPyramid, JointLimitsViability, TorqueLimits, WrenchBox
    from a3cqp_rl.control.tasks import (Admittance, CartesianAccelerationRegularizer, CartesianIK, ForceControl,
                                        JointCentering)

    by_type: dict[type, object] = {}
    for t in ctrl.tasks:
        if type(t) not in (CartesianIK, Admittance, ForceControl, JointCentering, CartesianAccelerationRegularizer) \
                or type(t) in by_type:
            return None, f"task {type(t).__name__} is not one of the default tasks (or appears twice)"
        by_type[type(t)] = t
    missing = [k.__name__ for k in (CartesianIK, Admittance, ForceControl, JointCentering) if k not in by_type]
    if missing:
        return None, f"tasks {missing} are missing"
    lims = ctrl.limits
    jl = ctrl.joint_limits
    expected = [JointLimitsViability, WrenchBox, FrictionPyramid]
    if not (len(lims) in (3, 4) and [type(x) for x in lims[:3]] == expected and lims[0] is jl
            and (len(lims) == 3 or (type(lims[3]) is TorqueLimits and lims[3].safe in (None, jl)))):
        return None, "limits are not (JointLimitsViability, WrenchBox, FrictionPyramid[, TorqueLimits])"
    ik, ac, jc = by_type[CartesianIK], by_type[Admittance], by_type[JointCentering]
    creg = by_type.get(CartesianAccelerationRegularizer)
    cfg, opt = ctrl.config, ctrl.options
    kp, kv = ik.gains(np.empty(0))  # (numpy arrays: `gains` returns them in the kind of its argument)
    tl = lims[3] if len(lims) == 4 else None
    p = Params(
        dt=ctrl.dt, cv=cfg.cv, cp=cfg.cp, kp=_vec(kp, 6), kv=_vec(kv, 6),
        lambda_d=ac.lambda_d, c_d=ac.c_d, ac_paper=float(ac.form == "paper"), f_d_max=ctrl.f_d_max,
        wrench_ff=float(opt.ik_wrench_feedforward), pd_pinv=float(opt.pd_projection == "pinv"),
        creg_gamma=0.0 if creg is None else creg.gamma,
        q_center=_vec(jc.q_center, 7), kq=jc.kq, jc_eps=jc.epsilon, jc_eps_n=jc.nullspace_weight,
        reg=opt.regularization, pinv_damping=opt.pinv_damping, nullspace_damping=opt.nullspace_damping,
        q_min=_vec(jl.q_min, 7), q_max=_vec(jl.q_max, 7), dq_max=_vec(jl.dq_max, 7), ddq_max=_vec(jl.ddq_max, 7),
        horizon=jl.horizon, target_total=float(jl.target == "total"), include_f_ext=float(jl.include_f_ext),
        brake_gain=jl.brake_gain, has_tau_stop=float(jl.tau_max is not None),
        tau_stop_max=_vec(jl.tau_max if jl.tau_max is not None else np.zeros(7), 7),
        torque_share=jl.torque_share, min_stop_fraction=jl.min_stop_fraction,
        wrench_max=_vec(lims[1].limit, 6), mu=lims[2].mu,
        has_torque_limits=float(tl is not None), torque_max=_vec(tl.tau_max if tl is not None else np.zeros(7), 7),
        torque_safe=float(tl is not None and tl.safe is not None),
        tau_clip=_vec(ctrl.tau_max, 7), leak=ctrl.dt * opt.desired_state_leak)
    return p, ""


def _bind(path: Path) -> ctypes.CDLL:
    """Load the compiled a3cqp_step and declare its functions (checking the C layouts against Params and INPUTS)."""
    lib = ctypes.CDLL(str(path))
    lib.a3cqp_params_size.restype = lib.a3cqp_input_size.restype = lib.a3cqp_rows.restype = ctypes.c_int64
    if lib.a3cqp_params_size() != ctypes.sizeof(Params):
        raise RuntimeError("a3cqp_params in a3cqp_step.c and native.Params differ")
    if lib.a3cqp_input_size() != sum(w for _, w in INPUTS):
        raise RuntimeError("the input row of a3cqp_step.c and native.INPUTS differ")
    lib.a3cqp_rows.argtypes = [ctypes.c_void_p]
    lib.a3cqp_assemble.argtypes = [ctypes.c_int64, *[ctypes.c_void_p] * 3]
    lib.a3cqp_torque.argtypes = [ctypes.c_int64, *[ctypes.c_void_p] * 6]
    lib.a3cqp_assemble.restype = lib.a3cqp_torque.restype = None
    return lib


INPUTS = (("q", 7), ("qd", 7), ("mass", 49), ("bias", 7), ("jac", 42), ("jdot_qdot", 6), ("twist", 6), ("pos", 3),
          ("rot", 9), ("weights", 18), ("f_d", 6), ("pos_d", 3), ("rot_d", 9), ("f_ext", 6), ("in_contact", 1),
          ("q_des", 7), ("qd_des", 7))
"""The per-arm input row of a3cqp_assemble (the IN_* offsets of the C file), in order: (name, width)."""

_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_CONTROL", _bind, _log, "a3cqp_rl.control: native controller step",
                       "the Python path")


def load() -> ctypes.CDLL | None:
    """The compiled a3cqp_step library, or None (A3CQP_NATIVE_CONTROL=0, or not built / stale: one warning)."""
    return _library.get()


def _reset() -> None:
    """Forget the loaded library (tests: re-read the environment on the next `load()`)."""
    _library.reset()


@dataclass(frozen=True)
class Assembled:
    """The QP of a step (P [N, 13, 13], c [N, 13], G [N, m, 13], h [N, m]) and what the torque law needs after it."""

    P: np.ndarray
    c: np.ndarray
    G: np.ndarray
    h: np.ndarray
    pd: np.ndarray
    """P W1 J [N, 7, 7] (eq. 5)."""
    pose_error: np.ndarray
    """e_x [N, 6] (m, rad)."""
    f_adm: np.ndarray
    """Admittance wrench reference [N, 6] (eq. 18)."""
    f_ctc: np.ndarray
    """Contact wrench reference [N, 6] (eq. 20)."""
    safe: np.ndarray
    """Viable brake q̈_safe [N, 7] (the fallback acceleration)."""
    packed: tuple[np.ndarray, np.ndarray]
    """The C call's input and output buffers (the torque law reads them)."""


class NativeStep:
    """The C step for one controller's parameters (numpy arrays in and out, float64, batch first)."""

    def __init__(self, lib: ctypes.CDLL, params: Params) -> None:
        self.lib, self.params = lib, params
        self._p = ctypes.addressof(params)
        self.rows = m = int(lib.a3cqp_rows(self._p))
        self._out_widths = (169, 13, 13 * m, m, 49, 6, 6, 6, 7)
        self._out_shapes = ((13, 13), (13,), (m, 13), (m,), (7, 7), (6,), (6,), (6,), (7,))
        self._layout: dict[int, list[tuple[int, int, tuple[int, ...]]]] = {}

    def _slices(self, n: int) -> list[tuple[int, int, tuple[int, ...]]]:
        """(start, stop, shape) of each output array in a batch-n output buffer (cached per n)."""
        out = self._layout.get(n)
        if out is None:
            out, start = [], 0
            for w, shape in zip(self._out_widths, self._out_shapes):
                out.append((start, start + n * w, (n, *shape)))
                start += n * w
            self._layout[n] = out
        return out

    def assemble(self, q: np.ndarray, qd: np.ndarray, mass: np.ndarray, bias: np.ndarray, jac: np.ndarray,
                 jdot_qdot: np.ndarray, twist: np.ndarray, pos: np.ndarray, rot: np.ndarray, weights: np.ndarray,
                 f_d: np.ndarray, pos_d: np.ndarray, rot_d: np.ndarray, f_ext: np.ndarray, in_contact: np.ndarray,
                 q_des: np.ndarray, qd_des: np.ndarray) -> Assembled:
        """build_context + build_qp of the default composition for N arms (shapes as A3CQPController.step)."""
        n = q.shape[0]
        # one packed copy of the inputs (order INPUTS): also makes strided views contiguous
        packed = np.concatenate([q, qd, mass.reshape(n, 49), bias, jac.reshape(n, 42), jdot_qdot, twist, pos,
                                 rot.reshape(n, 9), weights.reshape(n, 18), f_d, pos_d, rot_d.reshape(n, 9), f_ext,
                                 in_contact.reshape(n, 1), q_des, qd_des], axis=1, dtype=np.float64)
        sl = self._slices(n)
        out = np.empty(sl[-1][1])
        self.lib.a3cqp_assemble(n, self._p, address(packed), address(out))
        return Assembled(*(out[a:b].reshape(shape) for a, b, shape in sl), packed=(packed, out))

    def torque(self, x: np.ndarray, ok: np.ndarray, asm: Assembled) -> tuple[np.ndarray, ...]:
        """Eq. 4-7 (or the brake where not ok), the q*/q̇* relaxation and the clip: (τ, q̈*, f, q̈_pd, q*, q̇*, sat)."""
        n = x.shape[0]
        x = np.ascontiguousarray(x, dtype=np.float64)
        okc = np.ascontiguousarray(ok, dtype=np.uint8)
        out = np.empty(n * 42)  # τ | q̈* | f | q̈_pd | q* | q̇* | saturated (7 + 7 + 6 + 7 + 7 + 7 + 1)
        packed, asm_out = asm.packed
        self.lib.a3cqp_torque(n, self._p, address(packed), address(asm_out), address(x), address(okc), address(out))
        tau, qdd, f, qdd_pd, qs, qds = (out[n * a:n * b].reshape(n, b - a)
                                        for a, b in ((0, 7), (7, 14), (14, 20), (20, 27), (27, 34), (34, 41)))
        return tau, qdd, f, qdd_pd, qs, qds, out[41 * n:] != 0.0
