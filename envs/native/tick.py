"""PandaEnv's 1-kHz control period in one C call (`tick.c`): mj_step1, sensing, checks, controller, QP, hand, mj_step2.

Why native: with each piece of a control period in C (sensing, checks, controller, QP, hand), the Python around them
(~100 calls that check, pack and route arrays) is still ~0.5 ms of a ~2.2-ms period at 65 arms. `tick.c` calls the
same C functions with the same arguments in the same order, so its numbers are the Python period's bit for bit
(tests/test_tick_native.py); `PandaEnv._tick` stays the reference.

It runs where every piece is native and the period is the common one: a `PandaSim` (not sharded), ideal sensors
(no noise, bias or taring), the default controller composition in one level (`A3CQPController` or a
`PopulationController`). Where the controller's Python takes another
route within a period (a non-finite input, a QP not solved cleanly), the C call stops before the controller and the
rest of that period runs in Python. `A3CQP_NATIVE_TICK=0` switches it off; a library not built at install time logs
one warning and the Python period runs.

MuJoCo is called here without the bindings, so the call routes MuJoCo's errors as they do: an engine error inside a
step (e.g. its stack exhausted by a model's `<size memory>` too small) raises `mujoco.FatalError`, and a user's
`mjcb_*` callback that raised re-raises its own exception.
"""

from __future__ import annotations

import ctypes
import logging
from pathlib import Path
from typing import TYPE_CHECKING

import mujoco
import numpy as np
import torch

from a3cqp_rl.control import controller as controller_module
from a3cqp_rl.control import native as control_native
from a3cqp_rl.control.context import N_VARS
from a3cqp_rl.control.controller import SUBSET_MIN_IDLE, A3CQPController
from a3cqp_rl.control.population import PopulationController
from a3cqp_rl.native_build import LazyLibrary, address, contiguous, library_path
from a3cqp_rl.qp import native as qp_native
from a3cqp_rl.qp.solver import MAX_STEPS, QPSolution, solve_qp
from a3cqp_rl.robot import sense
from a3cqp_rl.robot.sim import PandaSim
from envs.native import hand as hand_native
from envs.native import period as period_native

if TYPE_CHECKING:
    from envs.panda import PandaEnv

__all__ = ["NativeTick", "native_tick", "numpy_tick", "SOURCE", "DONE", "BEFORE_CONTROLLER"]

SOURCE = Path(__file__).with_name("tick.c")
DONE, BEFORE_CONTROLLER, _ENGINE_ERROR = 0, 1, 2
"""`tick_run`'s results: the period ran whole; it stopped before the controller (the rest is Python's); MuJoCo
raised an error (raised here as the bindings raise it)."""

_log = logging.getLogger(__name__)
_p, _i, _d = ctypes.c_void_p, ctypes.c_int64, ctypes.c_double

_FIELDS = [
    ("n", _i), ("rows", _i),
    *((f, _p) for f in ("step1", "step2", "observe", "wrench", "measure", "checks", "assemble", "assemble_robots",
                        "solve", "torque", "hand", "push", "model", "sense_args", "period_args", "params", "hand_args",
                        "push_args", "data")),
    *((f, _i) for f in ("ncon_offset", "contact_offset", "contact_size", "dist_offset", "geom_offset", "nxfrc")),
    *((f, _p) for f in ("xfrc_applied", "ctrl", "qfrc_constraint", "qfrc_applied", "act", "dadr", "geom_arm", "q", "qd",
                        "bias", "mass", "f_env", "cs_pos", "cs_rot", "jt", "twist", "jdot_qdot", "tau_ext",
                        "tau_push", "pos", "rot", "f_ext", "ft", "f_ope", "r_handle", "handle_pos", "f_sum")),
    ("contact_threshold", _d),
    *((f, _p) for f in ("pen", "pen_max", "skip", "live", "excess", "speed", "joint", "bad", "weights", "f_d",
                        "pos_d", "rot_d", "f_ext_limits", "robot_rows", "leak_extra", "tau_max", "in_offsets")),
    ("in_size", _i),
    *((f, _p) for f in ("q_des", "qd_des", "packed", "asm_out", "warm", "qp_out", "tout", "tau", "strides")),
    ("tol", _d), ("max_steps", _i), ("cold", _i),
    *((f, _p) for f in ("idle", "saturated", "ok", "t", "noise")),
    ("noise_stride", _i), ("handle_force", _p), ("handle_torque", _p), ("dt", _d),
    ("sub", _p), ("nsub", _i), ("z0_sub", _p), ("leak_sub", _p),
    ("set_log", _p), ("global_log", _p), ("set_error", _p),
]


_HOOKS = {"env": {"_measure", "_control", "_native_checks", "_check_divergence", "_track_joint_limits",
                  "_log_diverged"},
          "sim": {"observe", "_observe_arrays", "push", "step", "max_penetration"},
          "ctrl": {"step", "_prepare", "_step_native", "_native_qp", "assemble_native", "_solve", "_report_fallback"}}
"""The methods the C period stands for: one replaced on its instance (a test's or a user's hook), or the controller
module's solve_qp replaced, keeps the Python period, which calls it."""


class _Args(ctypes.Structure):
    """`tick_args` of tick.c (the same field order)."""

    _fields_ = _FIELDS


def _fn(lib: ctypes.CDLL, name: str) -> int:
    return ctypes.cast(getattr(lib, name), ctypes.c_void_p).value


def _mujoco_library() -> ctypes.CDLL:
    """The libmujoco the bindings loaded (dlopen of the same file gives the same library)."""
    found = sorted(Path(mujoco.__file__).parent.glob("libmujoco.so*"))
    if not found:
        raise RuntimeError("no libmujoco.so next to the mujoco package")
    return ctypes.CDLL(str(found[0]))


def _data_layout() -> dict[str, int]:
    """Byte offsets in mjData of `ncon` and of the `contact` pointer, and mjContact's size and the offsets of its dist
    and geom1 (geom2 follows), found once on a scratch model with contacts (one layout per MuJoCo build)."""
    m = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><geom type="plane" size="1 1 1"/><body pos="0 0 0.05"><freejoint/>'
        '<geom type="box" size=".1 .1 .1"/></body></worldbody></mujoco>')
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    con = d.contact
    base = con.dist.__array_interface__["data"][0]
    geom1 = con.geom1.__array_interface__["data"][0] - base
    if d.ncon < 1 or con.geom2.__array_interface__["data"][0] - base != geom1 + 4:
        raise RuntimeError("unexpected mjContact layout")
    # ncon follows the timer statistics (mjdata.h); checked by writing two values through the bindings
    timer = d.timer.duration
    ncon = timer.__array_interface__["data"][0] + timer.strides[0] * len(timer) - d._address
    for value in (7, 3):
        d.ncon = value
        if np.frombuffer(ctypes.string_at(d._address + ncon, 4), dtype=np.int32)[0] != value:
            raise RuntimeError("mjData.ncon not found")
    d.ncon = 4
    # the contact pointer: mjdata.h's `arena` (which holds the same address: contacts start the arena) comes first
    words = np.frombuffer(ctypes.string_at(d._address + ncon, 2048), dtype=np.uint64)
    hits = np.flatnonzero(words == base)
    if len(hits) < 1:
        raise RuntimeError("mjData.contact not found")
    return {"ncon_offset": ncon, "contact_offset": ncon + 8 * int(hits[-1]), "contact_size": con.dist.strides[0],
            "dist_offset": 0, "geom_offset": geom1}


def _error_routing(mj: ctypes.CDLL) -> dict[str, int]:
    """MuJoCo's thread-local error routing that the bindings use (private entry points): the log-handler setter and
    the global handler's getter from MuJoCo 4.0, the error-function setter before."""
    names = {"set_log": "_mjPRIVATE_setTlsLogHandler", "global_log": "_mjPRIVATE_getGlobalLogHandler",
             "set_error": "_mjPRIVATE__set_tls_error_fn"}
    found = {key: _fn(mj, name) for key, name in names.items() if hasattr(mj, name)}
    if "set_log" in found and "global_log" in found:
        return {"set_log": found["set_log"], "global_log": found["global_log"]}
    if "set_error" in found:
        return {"set_error": found["set_error"]}
    raise RuntimeError("MuJoCo's error routing (the entry points its Python bindings use) is not in this libmujoco")


def _bind(path: Path) -> dict:
    """The tick library, MuJoCo's step halves, the other pieces' entry points and mjData's layout."""
    # PyDLL: the call keeps the GIL and raises an exception a Python callback of MuJoCo's left set (an mjcb_* that
    # raised), as the bindings re-raise it
    lib = ctypes.PyDLL(str(path))
    lib.tick_args_size.restype = ctypes.c_int64
    if lib.tick_args_size() != ctypes.sizeof(_Args):
        raise RuntimeError("tick_args in tick.c and envs.native.tick differ")
    lib.tick_run.argtypes = [_p, _i, _i, _i, _p]
    lib.tick_run.restype = _i
    lib.tick_error_message.restype = ctypes.c_char_p
    mj = _mujoco_library()
    qp_path = library_path(qp_native.SOURCE)
    if qp_path is None:
        raise RuntimeError("the QP library was not built")
    return {"lib": lib, "mj": mj, "qp": ctypes.CDLL(str(qp_path)), "layout": {**_data_layout(), **_error_routing(mj)}}


_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_TICK", _bind, _log, "envs: the control period in one C call",
                       "the Python control period")


def numpy_tick():  # noqa: ANN201
    """Within the block new PandaEnvs take the Python control period (e.g. the reference of a test)."""
    return _library.off()


class NativeTick:
    """One PandaEnv's control period in C: `prepare` once per agent period (its inputs and masks), `run` per control
    period (which sets the env's measurement attributes as `_measure` does: new arrays each period)."""

    def __init__(self, bound: dict, env: PandaEnv, libs: dict) -> None:
        sim, ctrl, n = env.sim, env.ctrl, env.num_envs
        self.env, self.n, self._lib = env, n, bound["lib"]
        step = ctrl._native
        self._m = m = step.rows
        a = self.args = _Args()
        for name, value in bound["layout"].items():
            setattr(a, name, value)
        a.n, a.rows, a.dt = n, m, env.dt
        a.step1, a.step2 = _fn(bound["mj"], "mj_step1"), _fn(bound["mj"], "mj_step2")
        a.observe, a.wrench = _fn(libs["sense"], "sense_observe"), _fn(libs["sense"], "sense_wrench")
        a.measure, a.checks = _fn(libs["period"], "period_measure"), _fn(libs["period"], "period_checks")
        a.assemble, a.assemble_robots = _fn(step.lib, "a3cqp_assemble"), _fn(step.lib, "a3cqp_assemble_robots")
        a.torque, a.solve = _fn(step.lib, "a3cqp_torque"), _fn(bound["qp"], "gi_qp_solve")
        a.hand, a.push = _fn(libs["hand"], "hand_wrench"), _fn(libs["hand"], "hand_push")
        d = sim.data
        a.model, a.data = sim.model._address, d._address
        a.sense_args = ctypes.addressof(sim._native_observe._keep[1])
        a.period_args = ctypes.addressof(env._period._args)
        a.params = step._p
        a.hand_args, a.push_args = ctypes.addressof(env._hand._args), ctypes.addressof(env._hand._push)
        idx = {name: contiguous(getattr(sim, "_" + name), np.int64) for name in ("act", "dadr", "geom_arm")}
        self._keep = [idx]
        for name, arr in idx.items():
            setattr(a, name, address(arr))
        a.nxfrc = d.xfrc_applied.size
        for name in ("xfrc_applied", "ctrl", "qfrc_constraint", "qfrc_applied"):
            setattr(a, name, address(getattr(d, name)))
        for name in ("q", "qd", "bias", "mass", "f_env", "cs_pos", "cs_rot", "jt", "twist", "jdot_qdot", "tau_ext",
                     "tau_push"):
            arr = getattr(sim, "_" + name)
            if not arr.flags.c_contiguous or arr.dtype != np.float64:
                raise ValueError(f"PandaSim's {name} array must be C-contiguous float64 for the native period")
            setattr(a, name, address(arr))
        # this period's sensing: the tick's own arrays, copied to the env's attributes by `publish`
        self._out = {name: np.zeros((n, w)) for name, w in (("pos", 3), ("rot", 9), ("f_ext", 6), ("ft", 6),
                                                              ("f_ope", 6), ("r_handle", 3), ("handle_pos", 3))}
        for name, arr in self._out.items():
            setattr(a, name, address(arr))
        a.contact_threshold = ctrl.options.contact_force_threshold
        self._pen, self._bad = np.zeros(n), np.zeros(n, dtype=np.uint8)
        a.pen, a.bad = address(self._pen), address(self._bad)
        # the controller's buffers: q*, q̇* and the warm start are published to the controller (written in place)
        offsets, start = [], 0
        for _, width in step.lib.inputs:
            offsets.append(start)
            start += width
        self._in_offsets = np.array(offsets, dtype=np.int64)
        if [name for name, _ in step.lib.inputs] != ["q", "qd", "mass", "bias", "jac", "jdot_qdot", "twist", "pos",
                                                        "rot", "weights", "f_d", "pos_d", "rot_d", "f_ext",
                                                        "in_contact", "q_des", "qd_des", "f_ext_limits"]:
            raise RuntimeError("a3cqp_step.c's input table is not the one tick.c packs")
        a.in_offsets, a.in_size = address(self._in_offsets), start
        self._packed = np.zeros((n, start))
        self._asm = np.zeros(n * sum(step._out_widths))
        nq = N_VARS  # the QP's variables (q̈*, f)
        self._warm_buf, self._qp_out = np.zeros(n * (3 * nq + m + 2)), np.zeros(n * (3 * nq + m + 2))
        self._tout, self._ok = np.zeros(n * 42), np.ones(n, dtype=np.uint8)
        self._z0_sub, self._leak_sub = np.zeros(n * (m + 2 * nq)), np.zeros(n * 6)
        a.z0_sub, a.leak_sub = address(self._z0_sub), address(self._leak_sub)
        self._strides = np.array([nq * nq, nq, 0, 0, m * nq, m, nq, nq, m + 2 * nq], dtype=np.int64)
        self._q_des, self._qd_des = np.zeros((n, 7)), np.zeros((n, 7))
        self._tau_max = contiguous(ctrl._tau_max_np)
        for name, arr in (("packed", self._packed), ("asm_out", self._asm), ("warm", self._warm_buf),
                          ("qp_out", self._qp_out), ("tout", self._tout), ("ok", self._ok), ("strides", self._strides),
                          ("q_des", self._q_des), ("qd_des", self._qd_des), ("tau_max", self._tau_max)):
            setattr(a, name, address(arr))
        a.tol, a.max_steps = 1e-9, MAX_STEPS
        self._q_des_t, self._qd_des_t = torch.from_numpy(self._q_des), torch.from_numpy(self._qd_des)
        self._warm = QPSolution._from_buffer(self._warm_buf, address(self._warm_buf), n, nq, 0, m)
        self._ref = ctypes.byref(a)
        self._flags = ctypes.c_int64(0)
        self._flags_ref = ctypes.byref(self._flags)
        self._agent: list = []
        # the objects whose addresses the call holds: kept alive, and the C route only while the env still has them
        self._pieces = (sim, ctrl, step, env._hand, env._period, sim._native_observe, sim.model, sim.data)
        self.ready = False
        self.diverged = False
        self.periods = {"whole": 0, "python_controller": 0, "python": 0}
        """Control periods run whole in C, those whose controller, hand and mj_step2 ran in Python, those run all
        in Python (from `prepare`'s first; diagnostics)."""

    # ------------------------------------------------------------------ per agent period
    def prepare(self, weights: torch.Tensor, f_d: torch.Tensor, pos_d: torch.Tensor, rot_d: torch.Tensor) -> bool:
        """Bind this agent period's controller inputs ([N, 6, 3], [N, 6], [N, 3], [N, 3, 3]) and masks; False where
        the period is not the common one (then `PandaEnv._tick` runs in Python)."""
        env, ctrl, a, n = self.env, self.env.ctrl, self.args, self.n
        self.ready = False
        if not self._same_pieces():
            return False
        if type(ctrl) not in (A3CQPController, PopulationController) or ctrl._native is None or not ctrl._numpy_ok:
            return False
        if not ctrl._native_fits() or ctrl._native_for != (tuple(map(id, ctrl.tasks)), tuple(map(id, ctrl.limits))):
            return False
        population = type(ctrl) is PopulationController
        if population and len(ctrl._robot_rows) != 1:
            return False
        idle = env.parked
        w = weights * ctrl._weight_on if population else weights
        keep = [contiguous(t.numpy()) for t in (w, f_d, pos_d, rot_d)]
        for name, arr in zip(("weights", "f_d", "pos_d", "rot_d"), keep):
            setattr(a, name, address(arr))
        held = env.operator.active if env.pcfg.joint_limits_f_ext == "operator" else np.zeros(n, dtype=bool)
        keep.append(held.astype(np.float64))
        a.f_ext_limits = address(keep[-1])
        if population:
            keep.append(contiguous(ctrl._robot_rows[0]))
            a.robot_rows = address(keep[-1])
        else:
            a.robot_rows = None
        if env._idle_leak is not None:
            keep.append(contiguous(ctrl._check_leak_extra(torch.from_numpy(env._idle_leak), env.q)))
            a.leak_extra = address(keep[-1])
        else:
            a.leak_extra = None
        a.idle, a.sub, a.nsub = None, None, 0
        if idle.any():
            keep.append(idle.view(np.uint8).copy())
            a.idle = address(keep[-1])
            if not population and int(idle.sum()) >= SUBSET_MIN_IDLE:  # the controller computes the others only
                keep.append(np.flatnonzero(~idle).astype(np.int64))
                a.sub, a.nsub = address(keep[-1]), len(keep[-1])
        a.saturated = address(ctrl.saturated_periods) if population else None
        if population and (ctrl.saturated_periods.dtype != np.int64 or not ctrl.saturated_periods.flags.c_contiguous):
            return False
        for name, arr in (("pen_max", env.max_penetration), ("excess", env.joint_limit_excess),
                          ("speed", env.joint_speed_ratio),
                          ("joint", env.joint_limit_joint), ("tau", env.tau), ("t", env.t),
                          ("handle_force", env.handle_force), ("handle_torque", env._handle_torque)):
            setattr(a, name, address(arr))
        hand = env._noise.get("hand")
        if hand is not None:
            keep.append(contiguous(hand))
            a.noise, a.noise_stride = address(keep[-1]), 3 * hand.shape[1]
        else:
            a.noise, a.noise_stride = None, 0
        a.f_sum = None if env._f_sum is None else address(env._f_sum)
        self._agent = keep
        self.masks()
        ctrl.residuals = {}
        self.ready = True
        return True

    def _same_pieces(self) -> bool:
        """Whether the env still has the sim (and its MuJoCo model and data), controller, hand, period and read-out
        this call was built on, and none of the methods it stands for is replaced on the instance (a caller's hook
        then sees its calls)."""
        env = self.env
        sim, ctrl, step, hand, period, observe, model, data = self._pieces
        if env.sim is not sim or env.ctrl is not ctrl or ctrl._native is not step or env._hand is not hand:
            return False
        if sim.model is not model or sim.data is not data:
            return False
        if (env._period is not period or sim._native_observe is not observe
                or controller_module.solve_qp is not solve_qp):
            return False
        return not (_HOOKS["env"] & vars(env).keys() or _HOOKS["sim"] & vars(sim).keys()
                    or _HOOKS["ctrl"] & vars(ctrl).keys())

    def masks(self) -> None:
        """The arms the checks skip and those in their episode (again after an arm diverges)."""
        env = self.env
        self._skip = (env.diverged | env.parked).view(np.uint8).copy()
        self._live = env._in_episode().view(np.uint8).copy()
        self.args.skip, self.args.live = address(self._skip), address(self._live)

    # ------------------------------------------------------------------ per control period
    def run(self, k: int) -> int:
        """Control period k of the agent period: DONE, BEFORE_CONTROLLER (sensing and checks done; the controller,
        the hand and mj_step2 are the caller's), or −1 (nothing ran: the whole period is the caller's). The arms
        newly diverged are in `bad_codes()`."""
        env, ctrl, a = self.env, self.env.ctrl, self.args
        if ctrl.q_des is not self._q_des_t or ctrl.qd_des is not self._qd_des_t:
            if ctrl.q_des is None:
                return self._stop_early()
            np.copyto(self._q_des, ctrl.q_des.numpy())
            np.copyto(self._qd_des, ctrl.qd_des.numpy())
            ctrl.q_des, ctrl.qd_des = self._q_des_t, self._qd_des_t
        warm = ctrl._warm
        if warm is not self._warm:
            if warm is None:
                a.cold = 1
            elif warm._buf is not None and warm._dims == self._warm._dims:
                np.copyto(self._warm_buf, warm._buf)
                a.cold = 0
            else:
                return self._stop_early()
        else:
            a.cold = 0
        sim, op = env.sim, env.operator
        hk = op._k
        op._k = (hk + 1) % op._lag
        result = self._lib.tick_run(self._ref, k, hk, sim._pushed, self._flags_ref)
        if result == _ENGINE_ERROR:
            raise mujoco.FatalError(self._lib.tick_error_message().decode(errors="replace"))
        flags = self._flags.value
        self.publish()
        self.periods["whole" if result == DONE else "python_controller"] += 1
        if result == DONE:
            sim._pushed = bool(flags & 2)
            if warm is not self._warm:
                ctrl._warm = self._warm
        else:
            op._k = hk  # (the hand has not run: Python's runs it)
            sim._pushed = False
        self.diverged = bool(flags & 1)
        return result

    def _stop_early(self) -> int:
        """Not this period in C: nothing ran (the caller runs the whole period in Python)."""
        self.diverged = False
        self.periods["python"] += 1
        return -1

    def bad_codes(self) -> np.ndarray:
        """The codes (envs.native.period.WHY) of the arms that diverged in the last period [N]."""
        return self._bad.copy()

    def publish(self) -> None:
        """The env's measurement attributes from the last period (new arrays, as `PandaEnv._measure` makes: a caller
        may keep them)."""
        env, o, sim = self.env, self._out, self.env.sim
        env.q, env.qd, env._twist = sim._q, sim._qd, sim._twist
        env.pos, env.rot = o["pos"].copy(), o["rot"].reshape(self.n, 3, 3).copy()
        env.f_ext, env.f_env = o["f_ext"].copy(), o["ft"].copy()
        env.f_env_true = env.f_env
        env.f_ope, env._r_handle, env.handle_pos = o["f_ope"].copy(), o["r_handle"].copy(), o["handle_pos"].copy()


def native_tick(env: PandaEnv) -> NativeTick | None:
    """NativeTick of `env`, or None where the library is off or absent or the env is not the common case (a sharded
    sim, sensor errors, a piece in numpy, a controller the C step does not translate)."""
    if not isinstance(env.sim, PandaSim) or env._hand is None or not env._hand.pushes or env._period is None:
        return None
    if not env.pcfg.sensors.ideal:
        return None
    if env.sim._native_observe is None or env.sim._cs is None or env.ctrl._native is None:
        return None
    libs = {"sense": sense._library.get(), "period": period_native._library.get(), "hand": hand_native._library.get()}
    if any(v is None for v in libs.values()) or control_native.load() is None or qp_native.load() is None:
        return None
    bound = _library.get()
    return None if bound is None else NativeTick(bound, env, libs)
