"""A3CQP tasks (eq. 8, 10-11, 17-18, 20-21, 23) and frame helpers: each equation checked on random batches."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from a3cqp_rl.control import A3CQPController, Admittance, CartesianIK, ControllerOptions, JointCentering
from a3cqp_rl.control.context import ControlContext
from a3cqp_rl.control.exceptions import ControlShapeError, InvalidGainError
from a3cqp_rl.control.frames import block_rotation, pose_error, rotation_log, weights_to_world
from a3cqp_rl.control.tasks import CartesianAccelerationRegularizer, ForceControl, Residual
from a3cqp_rl.robot import PANDA_LIMITS, mujoco_dynamics

B = 32


def random_rotations(n: int, gen: torch.Generator) -> torch.Tensor:
    """Uniform-ish random rotations [n, 3, 3] via QR of Gaussian matrices."""
    Q, R = torch.linalg.qr(torch.randn(n, 3, 3, generator=gen, dtype=torch.float64))
    Q = Q * torch.sign(torch.diagonal(R, dim1=-2, dim2=-1)).unsqueeze(-2)
    return Q * torch.sign(torch.linalg.det(Q)).view(n, 1, 1)


def make_context(n: int = B, seed: int = 0, **over) -> tuple[A3CQPController, ControlContext]:
    """A controller and a context at random states, weights, references and external wrenches."""
    gen = torch.Generator().manual_seed(seed)
    lim = PANDA_LIMITS.tensors()
    q = lim["q_min"] + 0.1 + (lim["q_max"] - lim["q_min"] - 0.2) * torch.rand(n, 7, generator=gen, dtype=torch.float64)
    qd = 0.5 * torch.randn(n, 7, generator=gen, dtype=torch.float64)
    ctrl = A3CQPController(n, options=over.pop("options", None))
    mass, _ = mujoco_dynamics(ctrl.model.mj_model, q, qd)
    w = torch.softmax(2.0 * torch.randn(n, 6, 3, generator=gen, dtype=torch.float64), dim=-1)
    f_d = 25.0 * torch.rand(n, 6, generator=gen, dtype=torch.float64)
    pos, rot = ctrl.model.fk(q)
    pos_d = pos + 0.05 * torch.randn(n, 3, generator=gen, dtype=torch.float64)
    f_ext = 10.0 * torch.randn(n, 6, generator=gen, dtype=torch.float64)
    ctrl.reset(q + 0.01 * torch.randn(n, 7, generator=gen, dtype=torch.float64), qd)
    in_contact = torch.rand(n, generator=gen) < 0.5
    args = dict(q=q, qd=qd, mass=mass, weights=w, f_d=f_d, pos_d=pos_d, rot_d=rot, f_ext=f_ext, in_contact=in_contact)
    args.update(over)
    return ctrl, ctrl.build_context(**args)


def mv(M: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    return (M @ v.unsqueeze(-1)).squeeze(-1)


# ---------------------------------------------------------------------------------------------- frames
def test_weights_to_world_eq8() -> None:
    gen = torch.Generator().manual_seed(1)
    R = random_rotations(B, gen)
    D = block_rotation(R)
    assert torch.allclose(D @ D.transpose(-1, -2), torch.eye(6, dtype=torch.float64).expand(B, 6, 6), atol=1e-12)
    w = torch.rand(B, 6, generator=gen, dtype=torch.float64)
    W = weights_to_world(D, w)
    assert torch.allclose(W, W.transpose(-1, -2), atol=1e-12)
    # W = D diag(w) Dᵀ: the eigenvalues are the local weights, the eigenvectors the local axes in world
    assert torch.allclose(mv(W, D[..., :, 2]), w[:, 2:3] * D[..., :, 2], atol=1e-12)
    assert torch.allclose(torch.linalg.eigvalsh(W), torch.sort(w, dim=-1).values, atol=1e-12)
    # equal weights on all axes are rotation invariant
    assert torch.allclose(weights_to_world(D, torch.full((B, 6), 0.3, dtype=torch.float64)),
                          0.3 * torch.eye(6, dtype=torch.float64).expand(B, 6, 6), atol=1e-12)


@pytest.mark.parametrize("angle", [0.0, 1e-7, 0.3, 2.0, 3.1])
def test_rotation_log_inverts_axis_angle(angle: float) -> None:
    gen = torch.Generator().manual_seed(2)
    axis = torch.nn.functional.normalize(torch.randn(B, 3, generator=gen, dtype=torch.float64), dim=-1)
    K = torch.zeros(B, 3, 3, dtype=torch.float64)
    K[:, 0, 1], K[:, 0, 2], K[:, 1, 2] = -axis[:, 2], axis[:, 1], -axis[:, 0]
    K = K - K.transpose(-1, -2)
    R = torch.linalg.matrix_exp(angle * K)
    assert torch.allclose(rotation_log(R), angle * axis, atol=1e-9)


def test_pose_error_eq10() -> None:
    gen = torch.Generator().manual_seed(3)
    R = random_rotations(B, gen)
    p = torch.randn(B, 3, generator=gen, dtype=torch.float64)
    assert pose_error(p, R, p, R).abs().max() < 1e-12
    small = torch.linalg.matrix_exp(torch.tensor([[0.0, -0.01, 0.0], [0.01, 0.0, 0.0], [0.0, 0.0, 0.0]],
                                                 dtype=torch.float64))
    e = pose_error(p + 0.1, small @ R, p, R)
    assert torch.allclose(e[:, :3], torch.full((B, 3), 0.1, dtype=torch.float64))
    assert torch.allclose(e[:, 3:], torch.tensor([0.0, 0.0, 0.01], dtype=torch.float64).expand(B, 3), atol=1e-12)


# ---------------------------------------------------------------------------------------------- residuals
def test_residual_objective_equals_weighted_norm() -> None:
    gen = torch.Generator().manual_seed(4)
    A = torch.randn(B, 6, 13, generator=gen, dtype=torch.float64)
    b = torch.randn(B, 6, generator=gen, dtype=torch.float64)
    L = torch.randn(B, 6, 6, generator=gen, dtype=torch.float64)
    W = L @ L.transpose(-1, -2)
    H, c = Residual(A=A, b=b, W=W).objective()
    assert torch.equal(Residual(A=A, b=b, W=W).rows(), A)
    Hi, ci = Residual(A=None, b=b, W=W, col=7).objective()  # identity rows on the wrench block
    Ai = Residual(A=None, b=b, W=W, col=7).rows()
    assert torch.allclose(Hi, Ai.transpose(-1, -2) @ W @ Ai) and torch.allclose(ci, -mv(Ai.transpose(-1, -2) @ W, b))
    x = torch.randn(B, 13, generator=gen, dtype=torch.float64)
    r = mv(A, x) - b
    cost = 0.5 * (r * mv(W, r)).sum(-1)
    quad = 0.5 * (x * mv(H, x)).sum(-1) + (c * x).sum(-1) + 0.5 * (b * mv(W, b)).sum(-1)
    assert torch.allclose(cost, quad, rtol=1e-10, atol=1e-9)


def test_ik_reference_eq10_11() -> None:
    ctrl, ctx = make_context(seed=5)
    ik = CartesianIK(kp=150.0, k_theta=20.0)
    kp, kv = ik.gains(ctx.q)
    assert torch.allclose(kv, 2.0 * kp.sqrt()) and kp.tolist() == [150.0] * 3 + [20.0] * 3
    xdd_d = kp * ctx.pose_error - kv * ctx.kin.twist
    # the least-norm q̈ with J q̈ = ẍ_d − J̇q̇ − Λ⁻¹ f_ff zeroes the IK residual: out of contact, the wrench that
    # AC/FC will command is fed forward (J q̈ + Λ⁻¹ f_ff + J̇q̇ = ẍ_d); f_ff = 0 in contact
    assert ctx.wrench_feedforward is None
    f_ff = ctrl.wrench_feedforward(ctx) * (~ctx.in_contact).double().unsqueeze(-1)
    assert f_ff[~ctx.in_contact].abs().max() > 1.0
    ctx = dataclasses.replace(ctx, wrench_feedforward=f_ff)
    res = ik.residual(ctx)
    target = xdd_d - ctx.kin.jdot_qdot - mv(ctx.cart_inertia_inv, f_ff)
    qdd = torch.linalg.lstsq(ctx.kin.jac, target.unsqueeze(-1)).solution.squeeze(-1)
    assert (mv(res.A, qdd) - res.b).abs().max() < 1e-9 and res.col == 0
    assert res.W is ctx.W1
    with pytest.raises(InvalidGainError):
        CartesianIK(kp=-1.0)


def test_admittance_closed_loop_is_eq17() -> None:
    """With f = f_adm, eq. 16 Λ(ẍ − J̇q̇) = f + f_ext gives Λd ẍ + Cd ẋ = f_ext (eq. 17) for the consistent form."""
    ctrl, ctx = make_context(seed=6)
    ac = Admittance(lambda_d=5.0, c_d=7.0)
    f_adm = ac.admittance_wrench(ctx)
    lam = ctx.cart_inertia
    xdd = torch.linalg.solve(lam, f_adm + ctx.f_ext) + ctx.kin.jdot_qdot  # eq. 16
    assert torch.allclose(5.0 * xdd + 7.0 * ctx.kin.twist, ctx.f_ext, atol=1e-6)
    # the printed eq. 18 differs by the damping term only: −Cd ẋ instead of −ΛΛd⁻¹ Cd ẋ
    f_paper = Admittance(lambda_d=5.0, c_d=7.0, form="paper").admittance_wrench(ctx)
    assert torch.allclose(f_paper - f_adm, mv(lam / 5.0, 7.0 * ctx.kin.twist) - 7.0 * ctx.kin.twist, atol=1e-8)
    with pytest.raises(InvalidGainError):
        Admittance(lambda_d=0.0)


def test_cartesian_inertia_is_inverse_of_j_binv_jt() -> None:
    ctrl, ctx = make_context(seed=7)
    mass, J = ctx.mass, ctx.kin.jac
    lam_inv = J @ torch.linalg.solve(mass, J.transpose(-1, -2))
    eye = torch.eye(6, dtype=torch.float64).expand(B, 6, 6)
    damping = ctrl.options.pinv_damping  # Λ = (J B⁻¹ Jᵀ + λ I)⁻¹ stays finite at singularities
    assert torch.allclose(ctx.cart_inertia @ (lam_inv + damping * eye), eye, atol=1e-8)
    assert torch.allclose(ctx.cart_inertia, ctx.cart_inertia.transpose(-1, -2))


def test_force_control_eq20_21() -> None:
    ctrl, ctx = make_context(seed=8)
    f_ctc = ForceControl().contact_wrench(ctx)
    # eq. 20: rotate the local wrench; eq. 21: 0 ≤ f_d ≤ f̄_d = 20 N (the random f_d go up to 25 N)
    assert ctx.f_d_local.max() <= 20.0 and ctx.f_d_local.min() >= 0.0
    assert torch.allclose(f_ctc[:, :3], mv(ctx.D[:, :3, :3], ctx.f_d_local[:, :3]))
    assert torch.allclose(f_ctc.norm(dim=-1), ctx.f_d_local.norm(dim=-1))


def test_joint_centering_moves_only_the_null_space() -> None:
    """Unconstrained IK + JC with w1 = 1: J q̈ meets the IK target and N q̈ = N q̈_d (strict null-space priority)."""
    w = torch.zeros(B, 6, 3, dtype=torch.float64)
    w[..., 0] = 1.0
    ctrl, ctx = make_context(seed=9, weights=w)
    ik, jc = CartesianIK(), JointCentering(torch.zeros(7, dtype=torch.float64), kq=10.0, epsilon=1e-4,
                                          nullspace_weight=1e-3)
    H1, c1 = ik.residual(ctx).objective()
    H2, c2 = jc.residual(ctx).objective()
    H = (H1 + H2)[:, :7, :7] + 1e-12 * torch.eye(7, dtype=torch.float64)
    qdd = -torch.linalg.solve(H, (c1 + c2)[:, :7])
    target = ik.desired_acceleration(ctx) - ctx.kin.jdot_qdot
    qdd_d = jc.desired_acceleration(ctx)
    assert torch.allclose(qdd_d, 10.0 * (0.0 - ctx.q) - 2.0 * math.sqrt(10.0) * ctx.qd)  # eq. 23
    # ε JᵀW1J pulls J q̈ toward J q̈_d by the fraction ε/(1 + ε) (eq. 1: JC is weighted like IK, scaled by ε)
    expected_task = (target + 1e-4 * mv(ctx.kin.jac, qdd_d)) / (1 + 1e-4)
    ok = torch.linalg.cond(ctx.kin.jac) < 50  # the damped J⁺ is exact away from singularities
    assert ok.sum() > B // 2
    assert (mv(ctx.kin.jac, qdd) - expected_task)[ok].abs().max() < 1e-5
    assert (mv(ctx.nullspace, qdd) - mv(ctx.nullspace, qdd_d))[ok].abs().max() < 1e-3  # |q̈_d| ~ 10-30
    assert mv(ctx.nullspace, qdd_d)[ok].abs().max() > 0.1  # the null-space check is not vacuous


def test_controller_rejects_wrong_shapes() -> None:
    ctrl = A3CQPController(2)
    z = torch.zeros
    with pytest.raises(ControlShapeError):
        ctrl.step(z(2, 7), z(2, 7), torch.eye(7).expand(2, 7, 7), z(2, 7), z(2, 6), z(2, 6), z(2, 3),
                  torch.eye(3).expand(2, 3, 3))


def test_wrench_feedforward_is_the_unconstrained_wrench_optimum() -> None:
    ctrl, ctx = make_context(seed=16)
    f_ff = ctrl.wrench_feedforward(ctx)
    ac, fc = ctrl.tasks[1].residual(ctx), ctrl.tasks[2].residual(ctx)
    # stationarity of ½‖f − f_adm‖²_W2 + ½‖f − f_ctc‖²_W3 + ½ r‖f‖² (eq. 24b without limits)
    grad = mv(ac.W, f_ff - ac.b) + mv(fc.W, f_ff - fc.b) + ctrl.options.regularization * f_ff
    assert grad.abs().max() < 1e-8


def test_weighted_sum_wrench_blend_is_eq35_per_local_axis() -> None:
    ctrl, ctx = make_context(seed=18, options=ControllerOptions(wrench_blend="weighted_sum"))
    f_ff = ctrl.wrench_feedforward(ctx)
    res = ctrl.task_residuals(ctx)
    ac, fc, ik_f = res["ac"], res["fc"], res["ik_wrench"]
    # stationarity of ½‖f − f_adm‖²_W2 + ½‖f − f_ctc‖²_W3 + ½‖f‖²_W1 + ½ r‖f‖²
    grad = mv(ac.W, f_ff - ac.b) + mv(fc.W, f_ff - fc.b) + mv(ik_f.W, f_ff) + ctrl.options.regularization * f_ff
    assert grad.abs().max() < 1e-8
    # w1 + w2 + w3 = 1 per local axis: f*^L = w2 f_adm^L + w3 f_ctc^L (eq. 35), up to the regularizer r
    local = lambda f: mv(ctx.D.mT, f)  # noqa: E731
    w = ctx.weights_local
    expected = w[..., 1] * local(ac.b) + w[..., 2] * local(fc.b)
    assert torch.allclose(local(f_ff), expected, atol=1e-3 * expected.abs().max().item())
    normalized, _ = make_context(seed=18)
    assert not torch.allclose(normalized.wrench_feedforward(_), f_ff, atol=1e-3)


def test_weighted_sum_wrench_blend_refuses_strict_levels() -> None:
    ctrl = A3CQPController(1, options=ControllerOptions(wrench_blend="weighted_sum"))
    with pytest.raises(InvalidGainError, match="weighted_sum"):
        ctrl.set_levels([1, 2, 2, 3, 3])
    with pytest.raises(InvalidGainError, match="wrench_blend"):
        A3CQPController(1, options=ControllerOptions(wrench_blend="sum"))


def test_cartesian_regularizer_weights_only_non_ik_axes() -> None:
    w = torch.zeros(B, 6, 3, dtype=torch.float64)
    w[:, :3, 0], w[:, 3:, 2] = 1.0, 1.0  # IK on the local forces' axes, FC on the rotations
    ctrl, ctx = make_context(seed=17, weights=w)
    reg = CartesianAccelerationRegularizer(gamma=0.5).residual(ctx)
    expected = 0.5 * weights_to_world(ctx.D, torch.tensor([0.0] * 3 + [1.0] * 3, dtype=torch.float64).expand(B, 6))
    assert torch.allclose(reg.W, expected, atol=1e-12)
    assert reg.b.abs().max() == 0.0


def test_options_select_the_paper_forms() -> None:
    ctrl = A3CQPController(1, options=ControllerOptions(admittance_form="paper", jc_nullspace_weight=0.0))
    assert ctrl.tasks[1].form == "paper" and ctrl.tasks[3].nullspace_weight == 0.0


def test_wrench_from_joint_torques_numpy_path_equals_torch_and_inverts_jt() -> None:
    from a3cqp_rl.control import wrench_from_joint_torques

    gen = torch.Generator().manual_seed(4)
    A = torch.randn(6, 7, 7, generator=gen, dtype=torch.float64)
    M = A @ A.mT + 7.0 * torch.eye(7, dtype=torch.float64)
    J = torch.randn(6, 6, 7, generator=gen, dtype=torch.float64)
    f = torch.randn(6, 6, generator=gen, dtype=torch.float64)
    tau = mv(J.mT, f)  # τ_ext = Jᵀ f: without damping the wrench comes back exactly
    fast = wrench_from_joint_torques(tau, J, M)  # CPU float64 without grad: the numpy path
    ref = wrench_from_joint_torques(tau, J, M.clone().requires_grad_()).detach()  # the torch path
    assert torch.allclose(fast, ref, atol=1e-10)
    assert torch.allclose(wrench_from_joint_torques(tau, J, M, damping=0.0), f, atol=1e-9)
    # robots with τ_ext = 0 skip the solves: the others' wrenches are the same bit for bit, theirs exactly 0
    tau[[1, 4]] = 0.0
    tau[2, 3] = float("nan")  # a NaN sensor reading still comes out as NaN, not as a quiet zero
    part = wrench_from_joint_torques(tau, J, M)
    assert torch.equal(part[[0, 3, 5]], fast[[0, 3, 5]]) and torch.equal(part[[1, 4]], torch.zeros(2, 6))
    assert torch.isnan(part[2]).all()
