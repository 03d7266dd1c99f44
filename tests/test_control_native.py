"""The native controller step (control/native, a3cqp_step.c) against the Python objects it translates."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

import a3cqp_rl.control.controller as controller_module
from a3cqp_rl.control import A3CQPController, ControllerOptions, native
from a3cqp_rl.control.exceptions import ControlShapeError, InvalidGainError
from a3cqp_rl.control.limits import WrenchBox
from a3cqp_rl.control.tasks import CartesianIK, ForceControl
from a3cqp_rl.qp import QPStatus
from a3cqp_rl.robot import PANDA_LIMITS, PandaModel, PandaSim, mujoco_dynamics

pytestmark = pytest.mark.skipif(native.load() is None, reason="no C compiler: the native step is not built")

N = 48


def random_inputs(n: int, seed: int, near_limits: bool = False) -> tuple[dict, PandaModel]:
    """Controller inputs at random states (a third of them at/over the position limits when `near_limits`)."""
    gen = torch.Generator().manual_seed(seed)
    f64 = torch.float64
    lim = PANDA_LIMITS.tensors()
    q = lim["q_min"] + 0.05 + (lim["q_max"] - lim["q_min"] - 0.1) * torch.rand(n, 7, generator=gen, dtype=f64)
    qd = 0.8 * torch.randn(n, 7, generator=gen, dtype=f64)
    if near_limits:  # at, inside and just past the position limits, moving toward them
        k = n // 3
        side = torch.rand(k, 7, generator=gen) < 0.5
        off = 0.02 * torch.rand(k, 7, generator=gen, dtype=f64) - 0.012
        q[:k] = torch.where(side, lim["q_max"] - off, lim["q_min"] + off)
        qd[:k] = torch.where(side, 1.0, -1.0) * 2.0 * torch.rand(k, 7, generator=gen, dtype=f64)
    model = PandaModel()
    mass, bias = mujoco_dynamics(model.mj_model, q, qd)
    kin = model.kinematics(q, qd)
    rot_d = torch.linalg.matrix_exp(torch.linalg.cross(  # the site orientation turned by up to ~0.5 rad
        torch.eye(3, dtype=f64).expand(n, 3, 3), 0.3 * torch.randn(n, 1, 3, generator=gen, dtype=f64).expand(n, 3, 3),
        dim=-1)) @ kin.rot
    inputs = dict(
        q=q, qd=qd, mass=mass, bias=bias, kin=kin,
        weights=torch.softmax(2.0 * torch.randn(n, 6, 3, generator=gen, dtype=f64), dim=-1),
        f_d=30.0 * torch.rand(n, 6, generator=gen, dtype=f64) - 5.0,
        pos_d=kin.pos + 0.05 * torch.randn(n, 3, generator=gen, dtype=f64), rot_d=rot_d,
        f_ext=10.0 * torch.randn(n, 6, generator=gen, dtype=f64),
        in_contact=torch.rand(n, generator=gen) < 0.5)
    return inputs, model


def pair(n: int, options: dict | None = None, model: PandaModel | None = None,
         q_des: tuple | None = None) -> tuple[A3CQPController, A3CQPController]:
    """A Python-backend and a native-backend controller with the same options and references q*, q̇*."""
    out = []
    for backend in ("python", "native"):
        ctrl = A3CQPController(n, model=model, options=ControllerOptions(backend=backend, **(options or {})))
        if q_des is not None:
            ctrl.reset(*q_des)
        out.append(ctrl)
    return out[0], out[1]


def assert_close(a: torch.Tensor | np.ndarray, b: torch.Tensor | np.ndarray, what: str, rtol: float = 1e-9) -> None:
    a, b = torch.as_tensor(np.asarray(a)), torch.as_tensor(np.asarray(b))
    err = ((a - b).abs() / (1.0 + b.abs())).max().item()
    assert err <= rtol, f"{what}: max relative difference {err:.2e}"


OPTION_VARIANTS = [
    {},
    {"admittance_form": "paper", "ik_wrench_feedforward": False, "pd_projection": "transpose"},
    {"joint_limit_target": "qdd", "torque_limits": False, "cartesian_regularization": 0.0},
    {"joint_limits_include_f_ext": True, "jc_nullspace_weight": 0.0, "desired_state_leak": 0.0},
    {"leak_axes": "per_axis", "desired_state_leak": 30.0},
    {"wrench_blend": "weighted_sum", "cartesian_regularization": 1.0},
]


@pytest.mark.parametrize("options", OPTION_VARIANTS, ids=["default", "paper-forms", "qdd-target", "f_ext", "per-axis-leak",
                                                          "weighted-sum"])
@pytest.mark.parametrize("near_limits", [False, True], ids=["inside", "near-limits"])
def test_native_qp_equals_the_python_objects(options: dict, near_limits: bool) -> None:
    inputs, model = random_inputs(N, seed=3 + near_limits, near_limits=near_limits)
    gen = torch.Generator().manual_seed(9)
    q_des = (inputs["q"] + 0.01 * torch.randn(N, 7, generator=gen, dtype=torch.float64),
             inputs["qd"] + 0.05 * torch.randn(N, 7, generator=gen, dtype=torch.float64))
    py, nat = pair(N, options, model, q_des)
    args = {k: v for k, v in inputs.items() if k not in ("kin", "bias")}
    ctx = py.build_context(**args, bias=inputs["bias"], kin=inputs["kin"])
    P, c, G, h = py.build_qp(ctx)
    a = {k: (v.numpy() if isinstance(v, torch.Tensor) else v) for k, v in inputs.items() if k != "kin"}
    kin = controller_module._kin_numpy(inputs["kin"])
    asm = nat.assemble_native(a["q"], a["qd"], a["mass"], a["bias"], a["weights"], a["f_d"], a["pos_d"], a["rot_d"],
                              a["f_ext"], a["in_contact"], kin)
    assert asm.G.shape == G.shape, "row count"
    for name, mine, ref in (("P", asm.P, P), ("c", asm.c, c), ("G", asm.G, G), ("h", asm.h, h),
                            ("pd", asm.pd, ctx.pd_matrix), ("pose error", asm.pose_error, ctx.pose_error),
                            ("f_adm", asm.f_adm, py.residuals["ac"].b), ("f_ctc", asm.f_ctc, py.residuals["fc"].b),
                            ("brake", asm.safe, py.joint_limits.safe_acceleration(ctx))):
        assert_close(mine, ref, name)
    if near_limits:  # the branches of the viable bounds were exercised: some rows bind at ±ddq_max
        ddq = py.joint_limits.ddq_max
        lb, ub = py.joint_limits.bounds_for(ctx)
        assert ((ub - ddq).abs() < 1e-12).any() or ((lb + ddq).abs() < 1e-12).any()


def test_per_robot_f_ext_limits_equal_in_c_and_python_and_equal_the_option_for_the_named_robots() -> None:
    inputs, model = random_inputs(N, seed=11, near_limits=True)
    mask = torch.arange(N) % 2 == 0
    q_des = (inputs["q"], inputs["qd"])
    py, nat = pair(N, {}, model, q_des)
    _, every = pair(N, {"joint_limits_include_f_ext": True}, model, q_des)
    args = {k: v for k, v in inputs.items() if k not in ("kin", "bias")}
    G_py, h_py = py.build_qp(py.build_context(**args, bias=inputs["bias"], kin=inputs["kin"], f_ext_limits=mask))[2:]
    a = {k: (v.numpy() if isinstance(v, torch.Tensor) else v) for k, v in inputs.items() if k != "kin"}
    kin = controller_module._kin_numpy(inputs["kin"])
    order = ("q", "qd", "mass", "bias", "weights", "f_d", "pos_d", "rot_d", "f_ext", "in_contact")
    masked = nat.assemble_native(*(a[k] for k in order), kin, f_ext_limits=mask.numpy())
    plain, all_arms = (c.assemble_native(*(a[k] for k in order), kin) for c in (nat, every))
    assert_close(masked.G, G_py, "G")
    assert_close(masked.h, h_py, "h")
    m = mask.numpy()
    np.testing.assert_array_equal(masked.h[m], all_arms.h[m])  # the named robots: as the option for every robot
    np.testing.assert_array_equal(masked.h[~m], plain.h[~m])  # the others: as without it
    assert not np.allclose(masked.h[m], plain.h[m])  # and it does something there
    with pytest.raises(ControlShapeError, match="f_ext_limits"):
        nat.step(inputs["q"], inputs["qd"], inputs["mass"], inputs["bias"], inputs["weights"], inputs["f_d"],
                 inputs["pos_d"], inputs["rot_d"], f_ext_limits=torch.ones(N))


def closed_loop(backend: str, steps: int, n: int = 3, seed: int = 0, scene: str = "",
                leak_axes: str = "min_w1", **options) -> tuple[list, A3CQPController]:
    """Torques and statuses of a closed loop with random weight switching every 20 ms and a push on arm 0."""
    gen = torch.Generator().manual_seed(seed)
    sim = PandaSim(n, control_site="tcp", scene=scene)
    ctrl = A3CQPController(n, options=ControllerOptions(backend=backend, leak_axes=leak_axes, **options))
    s = sim.observe()
    pos_d = s.kin.pos + 0.1 * (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5)
    rot_d = s.kin.rot.clone()
    out_log = []
    for k in range(steps):
        if k % 20 == 0:
            w = torch.softmax(3.0 * torch.randn(n, 6, 3, generator=gen, dtype=torch.float64), dim=-1)
            f_d = 10.0 * torch.rand(n, 6, generator=gen, dtype=torch.float64)
        s = sim.observe()
        f_ext = torch.zeros(n, 6, dtype=torch.float64)
        f_ext[0, 0] = 10.0 if 50 <= k < 150 else 0.0
        out = ctrl.step(s.q, s.qd, s.mass, s.bias, w, f_d, pos_d, rot_d, f_ext=f_ext, f_env=s.f_env, kin=s.kin)
        sim.step(out.tau)
        out_log.append(out)
    return out_log, ctrl


@pytest.mark.parametrize("leak_axes,options", [("min_w1", {}), ("per_axis", {}),
                                               ("per_axis", {"wrench_blend": "weighted_sum"})],
                         ids=["min_w1", "per_axis", "per_axis-weighted-sum"])
def test_native_closed_loop_equals_python(leak_axes: str, options: dict) -> None:
    py, _ = closed_loop("python", 300, leak_axes=leak_axes, **options)
    nat, ctrl = closed_loop("native", 300, leak_axes=leak_axes, **options)
    assert ctrl._native is not None
    for k, (a, b) in enumerate(zip(py, nat)):
        for f in ("tau", "qdd", "wrench", "qdd_pd", "pose_error", "f_adm", "f_ctc"):
            assert_close(getattr(b, f), getattr(a, f), f"step {k} {f}", rtol=1e-7)
        assert torch.equal(a.status, b.status) and torch.equal(a.fallback, b.fallback)
        assert torch.equal(a.saturated, b.saturated)


def test_native_fallback_equals_python(monkeypatch, caplog) -> None:
    inputs, model = random_inputs(4, seed=5)
    outs = []
    for backend in ("python", "native"):
        ctrl = A3CQPController(4, model=model, options=ControllerOptions(backend=backend))
        monkeypatch.setattr(controller_module, "solve_qp", lambda *a, **k: (_ for _ in ()).throw(RuntimeError("x")))
        with caplog.at_level(logging.WARNING):
            outs.append(ctrl.step(**inputs))
        assert ctrl.fallback_count == 4
    a, b = outs
    assert b.fallback.all() and (b.status == controller_module.SOLVER_ERROR).all()
    for f in ("tau", "qdd", "wrench", "qdd_pd"):
        assert_close(getattr(b, f), getattr(a, f), f)
    assert (b.wrench == 0).all() and (b.qdd_pd == 0).all()


def test_custom_composition_keeps_python_and_native_backend_says_why() -> None:
    class MyIK(CartesianIK):
        numpy_capable = True

    auto = A3CQPController(2, tasks=[MyIK(), ForceControl()])
    assert auto._native is None
    with pytest.raises(InvalidGainError, match="MyIK is not one of the default task"):
        A3CQPController(2, tasks=[MyIK(), ForceControl()], options=ControllerOptions(backend="native"))
    with pytest.raises(InvalidGainError, match="limits"):
        A3CQPController(2, extra_limits=[WrenchBox(5.0, 1.0)], options=ControllerOptions(backend="native"))
    with pytest.raises(InvalidGainError, match="backend"):
        A3CQPController(2, options=ControllerOptions(backend="fast"))  # type: ignore[arg-type]


def test_swapping_a_task_after_construction_turns_the_native_step_off(monkeypatch) -> None:
    inputs, model = random_inputs(2, seed=6)
    ctrl = A3CQPController(2, model=model)
    ctrl.tasks[0] = CartesianIK(kp=10.0, k_theta=5.0)  # a user tweaking a gain in place
    monkeypatch.setattr(A3CQPController, "_step_native", lambda *a, **k: pytest.fail("native step taken"))
    out = ctrl.step(**inputs)
    assert out.tau.shape == (2, 7) and ctrl.residuals  # the Python path ran (it keeps residuals)


def test_env_switch_disables_the_native_step(monkeypatch) -> None:
    monkeypatch.setenv("A3CQP_NATIVE_CONTROL", "0")
    native._reset()
    try:
        assert A3CQPController(1)._native is None
        with pytest.raises(InvalidGainError, match="C library is not available"):
            A3CQPController(1, options=ControllerOptions(backend="native"))
    finally:
        monkeypatch.undo()
        native._reset()
    assert A3CQPController(1)._native is not None


def test_parameters_come_from_the_objects_and_the_c_table() -> None:
    ctrl = A3CQPController(1)
    lib = native.load()
    c_names = [name for name, _ in lib.Params._fields_]
    assert len(c_names) == len(set(c_names)) == 41
    # every C field is set by exactly one owner: a task, a limit or the step
    owners = {}
    for piece in [*ctrl.tasks, *ctrl.limits]:
        kind, fields = piece.c_params()
        for name in fields:
            if name != "anchor":
                assert name not in owners, f"{name} set by {owners.get(name)} and {kind}"
                owners[name] = kind
    assert ctrl.tasks[0].c_params()[1]["kp"].tolist() == [150.0] * 3 + [20.0] * 3
    assert ctrl._native.params.kv[5] == pytest.approx(2.0 * 20.0 ** 0.5)
    assert ctrl._native.params.mu == ctrl.limits[2].mu
    fields, _ = ctrl._native_fields()
    assert set(fields) == set(c_names)
    with pytest.raises(ValueError, match=r"missing \['dt'\]"):
        native.NativeStep(lib, {k: v for k, v in fields.items() if k != "dt"})
    with pytest.raises(ValueError, match=r"unknown \['not_a_field'\]"):
        native.NativeStep(lib, {**fields, "not_a_field": 1.0})


def test_the_c_layout_is_checked_field_by_field() -> None:
    table = [("a", 0, 1), ("b", 1, 6), ("c", 7, 1)]
    assert [f[0] for f in native._struct(table, 64)._fields_] == ["a", "b", "c"]
    with pytest.raises(RuntimeError, match=r"a3cqp_params.c: C offset 64"):
        native._struct([("a", 0, 1), ("b", 1, 6), ("c", 8, 1)], 72)
    with pytest.raises(RuntimeError, match="C size 72"):
        native._struct(table, 72)


def test_subclasses_and_foreign_anchors_keep_the_python_objects() -> None:
    from a3cqp_rl.control.limits import JointLimitsViability, TorqueLimits

    class Scaled(ForceControl):  # may change the math: C must not claim it
        pass

    assert Scaled().c_params() is None and ForceControl().c_params() == ("fc", {})
    ctrl = A3CQPController(1)
    jl = ctrl.joint_limits
    other = JointLimitsViability(jl.q_min, jl.q_max, jl.dq_max + 0.5, jl.ddq_max, jl.dt)
    ctrl2 = A3CQPController(1, extra_limits=[])
    ctrl2.limits[3] = TorqueLimits(ctrl.tau_max, safe=other)
    step, why = ctrl2._make_native_step()
    assert step is None and "anchored to other joint limits" in why


@pytest.mark.parametrize("backend", ["auto", "python"])
def test_non_finite_state_on_the_first_call_brakes_with_gravity_compensation(backend: str, caplog) -> None:
    sim = PandaSim(2)
    s = sim.observe()
    ctrl = A3CQPController(2, options=ControllerOptions(backend=backend))
    w = torch.zeros(2, 6, 3, dtype=torch.float64)
    w[..., 0] = 1.0
    kin = ctrl.model.kinematics(s.q, s.qd)
    q = s.q.clone()
    q[1, 2] = float("nan")
    with caplog.at_level(logging.WARNING):
        out = ctrl.step(q, s.qd, s.mass, s.bias, w, torch.zeros(2, 6, dtype=torch.float64), kin.pos, kin.rot)
    assert out.status.tolist()[1] == controller_module.INVALID_INPUT and out.fallback.tolist() == [False, True]
    assert torch.isfinite(ctrl.q_des).all() and torch.isfinite(out.tau).all()
    assert torch.allclose(out.tau[1], s.bias[1], atol=1e-9)  # at rest the brake is pure gravity compensation
    out = ctrl.step(s.q, s.qd, s.mass, s.bias, w, torch.zeros(2, 6, dtype=torch.float64), kin.pos, kin.rot)
    assert out.status.tolist() == [0, 0] and not out.fallback.any() and torch.isfinite(out.tau).all()
    assert out.tau[1].abs().max() < 100.0


@pytest.mark.parametrize("backend", ["python", "native"])
def test_a_fallback_starts_only_the_failed_robots_qp_cold(monkeypatch, backend) -> None:
    inputs, model = random_inputs(6, seed=7, near_limits=True)
    ctrl = A3CQPController(6, model=model, options=ControllerOptions(backend=backend))
    real = controller_module.solve_qp
    kept = {}

    def robot_2_fails(*a, **k):
        sol = real(*a, **k)
        sol.status[2] = QPStatus.MAX_ITER
        kept["duals"] = torch.cat([sol.z, sol.z_lb, sol.z_ub], 1).clone()
        return sol

    monkeypatch.setattr(controller_module, "solve_qp", robot_2_fails)
    out = ctrl.step(**inputs)
    assert out.fallback.tolist() == [False, False, True, False, False, False]
    duals = torch.cat([ctrl._warm.z, ctrl._warm.z_lb, ctrl._warm.z_ub], 1)
    assert (kept["duals"][2] > 0).any() and (duals[2] == 0).all()  # robot 2's working set is gone
    others = [0, 1, 3, 4, 5]
    assert (kept["duals"][others] > 0).any() and torch.equal(duals[others], kept["duals"][others])


def test_native_regularizer_clips_ik_weights_above_one_as_python_does() -> None:
    """tasks.regularizer_ik_weight in C: an IK weight above 1 (a fixed controller's, plus FC's idle share)."""
    inputs, model = random_inputs(N, seed=5)
    w = inputs["weights"].clone()
    w[: N // 2, :, 0] += 0.6  # half the robots past 1 on some axes
    inputs["weights"] = w
    py, nat = pair(N, {}, model, (inputs["q"], inputs["qd"]))
    args = {k: v for k, v in inputs.items() if k not in ("kin", "bias")}
    P, c, G, h = py.build_qp(py.build_context(**args, bias=inputs["bias"], kin=inputs["kin"]))
    a = {k: (v.numpy() if isinstance(v, torch.Tensor) else v) for k, v in inputs.items() if k != "kin"}
    asm = nat.assemble_native(a["q"], a["qd"], a["mass"], a["bias"], a["weights"], a["f_d"], a["pos_d"], a["rot_d"],
                              a["f_ext"], a["in_contact"], controller_module._kin_numpy(inputs["kin"]))
    assert_close(asm.P, P, "P")
    assert_close(asm.c, c, "c")
