"""The controller's default step in C (`a3cqp_step.c`, built at install time): QP assembly and torque law.

Why native: on the CPU a control step of the Python objects is a few hundred numpy calls on 6×7 / 7×7 matrices at
0.5-3 µs each (and 10-25 µs each for 64 stacked matrices), while its arithmetic is ~20 k flops per arm.  The C file
is a line-by-line translation of the default composition (CartesianIK, Admittance, ForceControl, JointCentering,
the Cartesian regularizer; JointLimitsViability, WrenchBox, FrictionPyramid, TorqueLimits; eq. 4-7), so that
`A3CQPController` takes it when its tasks and limits are exactly those and the step runs on CPU float64; any other
composition (a custom task or limit, other devices, autograd through `build_context`) runs the Python objects, which
stay the reference (tests/test_control_native.py: agreement to 1e-9).  The QP itself is still `solve_qp`.

The objects hand their own parameters (`Task.c_params`, `Limit.c_params`); `compose_params` checks the composition
and the C file's field table defines the layout (one declaration).  `A3CQP_NATIVE_CONTROL=0` switches it off; a
library not built at install time (no compiler) or stale logs one warning and the Python path runs.
"""

from __future__ import annotations

import ctypes
import logging
from dataclasses import dataclass
from pathlib import Path
import numpy as np

from a3cqp_rl.native_build import LazyLibrary, address

__all__ = ["NativeStep", "Assembled", "load", "compose_params", "SOURCE"]

SOURCE = Path(__file__).with_name("a3cqp_step.c")

_log = logging.getLogger(__name__)

TASK_KINDS = ("ik", "ac", "fc", "jc")
"""The tasks C translates, each exactly once (plus the optional "creg", CartesianAccelerationRegularizer)."""
LIMIT_KINDS = ("joint_limits", "wrench_box", "friction")
"""The limits C translates, in this order (plus an optional trailing "torque_limits")."""
_ABSENT = {"creg_gamma": 0.0, "has_torque_limits": 0.0, "torque_max": np.zeros(7), "torque_safe": 0.0}
"""Fields of the optional pieces when they are absent."""


def compose_params(tasks: list[tuple[str, tuple[str, dict] | None]], limits: list[tuple[str, tuple[str, dict] | None]],
                   step: dict) -> tuple[dict | None, str]:
    """All fields of the C parameters, or (None, why) when the composition is not the one a3cqp_step.c translates.

    `tasks`, `limits`: (label, the piece's `c_params()`) in the controller's order; `step`: the step-level fields."""
    fields = dict(_ABSENT)
    kinds = []
    for label, part in [*tasks, *limits]:
        if part is None:
            return None, f"{label} is not one of the default task or limit classes (no C translation)"
    for _, (kind, part) in tasks:
        kinds.append(kind)
        fields.update(part)
    if sorted(kinds) not in (sorted(TASK_KINDS), sorted((*TASK_KINDS, "creg"))):
        return None, f"tasks {kinds} are not {list(TASK_KINDS)} (+ the Cartesian regularizer), each once"
    limits = [part for _, part in limits]
    kinds = [kind for kind, _ in limits]
    if kinds not in (list(LIMIT_KINDS), [*LIMIT_KINDS, "torque_limits"]):
        return None, f"limits {kinds} are not {list(LIMIT_KINDS)} (+ torque_limits)"
    for kind, part in limits:
        part = dict(part)
        if kind == "torque_limits":
            anchor = part.pop("anchor")
            if anchor is not None and not _same(anchor, limits[0]):
                return None, "the torque limits are anchored to other joint limits than the step's"
            part["has_torque_limits"] = 1.0
        fields.update(part)
    fields.update(step)
    return fields, ""


def _same(a: tuple[str, dict], b: tuple[str, dict]) -> bool:
    """Equal (kind, fields) pairs (array fields compared by value)."""
    return a[0] == b[0] and a[1].keys() == b[1].keys() and all(np.array_equal(a[1][k], b[1][k]) for k in a[1])


class _Field(ctypes.Structure):
    """`a3cqp_field` of a3cqp_step.c: one entry of its parameter or input-row table."""

    _fields_ = [("name", ctypes.c_char_p), ("offset", ctypes.c_int64), ("count", ctypes.c_int64)]


def _table(fn: ctypes._CFuncPtr) -> list[tuple[str, int, int]]:
    """(name, offset in doubles, count) of the table a3cqp_param_fields / a3cqp_input_fields returns."""
    ptr = ctypes.POINTER(_Field)()
    fn.argtypes, fn.restype = [ctypes.POINTER(ctypes.POINTER(_Field))], ctypes.c_int64
    n = fn(ctypes.byref(ptr))
    return [(ptr[i].name.decode(), int(ptr[i].offset), int(ptr[i].count)) for i in range(n)]


def _struct(table: list[tuple[str, int, int]], size: int) -> type[ctypes.Structure]:
    """A ctypes Structure of doubles laid out as the C table says (offsets and size checked field by field)."""
    d = ctypes.c_double
    cls = type("Params", (ctypes.Structure,), {"_fields_": [(n, d if c == 1 else d * c) for n, _, c in table]})
    for name, offset, _ in table:
        if getattr(cls, name).offset != 8 * offset:
            raise RuntimeError(f"a3cqp_params.{name}: C offset {8 * offset}, ctypes {getattr(cls, name).offset}")
    if ctypes.sizeof(cls) != size:
        raise RuntimeError(f"a3cqp_params: C size {size}, ctypes {ctypes.sizeof(cls)}")
    return cls


def _bind(path: Path) -> ctypes.CDLL:
    """Load the compiled a3cqp_step, declare its functions, and read its parameter and input layouts."""
    lib = ctypes.CDLL(str(path))
    lib.a3cqp_params_size.restype = lib.a3cqp_input_size.restype = lib.a3cqp_rows.restype = ctypes.c_int64
    lib.Params = _struct(_table(lib.a3cqp_param_fields), lib.a3cqp_params_size())
    lib.inputs = [(name, count) for name, _, count in _table(lib.a3cqp_input_fields)]
    offsets = [offset for _, offset, _ in _table(lib.a3cqp_input_fields)]
    if offsets != list(np.cumsum([0] + [c for _, c in lib.inputs[:-1]])) or sum(c for _, c in lib.inputs) != lib.a3cqp_input_size():
        raise RuntimeError("the input row of a3cqp_step.c is not packed in table order")
    lib.robot_fields = [(name, count) for name, _, count in _table(lib.a3cqp_robot_fields)]
    lib.a3cqp_robot_size.restype = ctypes.c_int64
    if sum(c for _, c in lib.robot_fields) != lib.a3cqp_robot_size():
        raise RuntimeError("the per-robot row of a3cqp_step.c is not packed in table order")
    lib.a3cqp_rows.argtypes = [ctypes.c_void_p]
    lib.a3cqp_assemble_robots.argtypes = [ctypes.c_int64, *[ctypes.c_void_p] * 4]
    lib.a3cqp_assemble_robots.restype = None
    lib.a3cqp_assemble.argtypes = [ctypes.c_int64, *[ctypes.c_void_p] * 3]
    lib.a3cqp_torque.argtypes = [ctypes.c_int64, *[ctypes.c_void_p] * 7]
    lib.a3cqp_assemble.restype = lib.a3cqp_torque.restype = None
    return lib


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

    def __init__(self, lib: ctypes.CDLL, fields: dict) -> None:
        """Bind `fields` (every field of the C parameters, from `compose_params`) for the calls of this step."""
        names = {name for name, _ in lib.Params._fields_}
        if fields.keys() != names:
            raise ValueError(f"C parameters: missing {sorted(names - fields.keys())}, unknown {sorted(fields.keys() - names)}")
        self.lib, self.params = lib, lib.Params()
        for name, ctype in lib.Params._fields_:
            value = fields[name]
            if ctype is ctypes.c_double:
                setattr(self.params, name, float(value))
            else:
                getattr(self.params, name)[:] = [float(v) for v in np.asarray(value, dtype=np.float64).reshape(-1)]
        self._p = ctypes.addressof(self.params)
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

    def pack(self, **inputs: np.ndarray) -> np.ndarray:
        """The inputs (entries of `lib.inputs`) as the C call's packed rows [N, IN_SIZE] (contiguous float64)."""
        n = inputs["q"].shape[0]
        return np.concatenate([inputs[name].reshape(n, width) for name, width in self.lib.inputs], axis=1,
                              dtype=np.float64)

    def assemble(self, robots: np.ndarray | None = None, packed: np.ndarray | None = None,
                 **inputs: np.ndarray) -> Assembled:
        """build_context + build_qp of the default composition for N arms.

        `inputs`: the entries of the C input table (`lib.inputs`: q, qd, mass, bias, jac, jdot_qdot, twist, pos, rot,
        weights, f_d, pos_d, rot_d, f_ext, in_contact, q_des, qd_des, f_ext_limits), batch first, shapes as
        A3CQPController.step (f_ext_limits [N]: 1.0 where the joint-limit rows count f_ext)
        (or `packed`, `pack`'s rows, to assemble several costs of the same inputs).  `robots` [N, R]: a population's
        per-robot rows (`robot_rows`: gains, and each task's share of this cost), else every arm runs the parameters."""
        # one packed copy of the inputs in the C table's order: also makes strided views contiguous
        packed = self.pack(**inputs) if packed is None else packed
        n = packed.shape[0]
        sl = self._slices(n)
        out = np.empty(sl[-1][1])
        if robots is None:
            self.lib.a3cqp_assemble(n, self._p, address(packed), address(out))
        else:
            robots = np.ascontiguousarray(robots, dtype=np.float64)
            if robots.shape != (n, self.lib.a3cqp_robot_size()):
                raise ValueError(f"per-robot rows must have shape ({n}, {self.lib.a3cqp_robot_size()}), "
                                 f"got {robots.shape}")
            self.lib.a3cqp_assemble_robots(n, self._p, address(packed), address(robots), address(out))
        return Assembled(*(out[a:b].reshape(shape) for a, b, shape in sl), packed=(packed, out))

    def robot_rows(self, **fields: np.ndarray) -> np.ndarray:
        """Per-robot rows [N, R] for `assemble(robots=...)` from the fields of `lib.robot_fields` ([N] or [N, count])."""
        missing = {name for name, _ in self.lib.robot_fields} ^ fields.keys()
        if missing:
            raise ValueError(f"per-robot fields: missing or unknown {sorted(missing)}")
        n = len(next(iter(fields.values())))
        return np.concatenate([np.asarray(fields[name], dtype=np.float64).reshape(n, count)
                               for name, count in self.lib.robot_fields], axis=1)

    def torque(self, x: np.ndarray, ok: np.ndarray, asm: Assembled,
               leak_extra: np.ndarray | None = None) -> tuple[np.ndarray, ...]:
        """Eq. 4-7 (or the brake where not ok), the q*/q̇* relaxation and the clip: (τ, q̈*, f, q̈_pd, q*, q̇*, sat).

        `leak_extra` [N, 6] (1/s): an extra rate of the per-axis relaxation along each axis of L (None: none)."""
        n = x.shape[0]
        x = np.ascontiguousarray(x, dtype=np.float64)
        okc = np.ascontiguousarray(ok, dtype=np.uint8)
        out = np.empty(n * 42)  # τ | q̈* | f | q̈_pd | q* | q̇* | saturated (7 + 7 + 6 + 7 + 7 + 7 + 1)
        packed, asm_out = asm.packed
        extra = None
        if leak_extra is not None:
            leak_extra = np.ascontiguousarray(leak_extra, dtype=np.float64)
            if leak_extra.shape != (n, 6):
                raise ValueError(f"leak_extra must have shape ({n}, 6), got {leak_extra.shape}")
            extra = address(leak_extra)
        self.lib.a3cqp_torque(n, self._p, address(packed), address(asm_out), address(x), address(okc), extra,
                              address(out))
        tau, qdd, f, qdd_pd, qs, qds = (out[n * a:n * b].reshape(n, b - a)
                                        for a, b in ((0, 7), (7, 14), (14, 20), (20, 27), (27, 34), (34, 41)))
        return tau, qdd, f, qdd_pd, qs, qds, out[41 * n:] != 0.0
