"""`A3CQPController.step(leak_extra=...)`: an extra per-axis rate of the q*, q̇* relaxation (leak_axes "per_axis")."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from a3cqp_rl.control import A3CQPController, ControllerOptions, native
from a3cqp_rl.control.exceptions import ControlShapeError, InvalidGainError
from a3cqp_rl.robot import PandaSim

from test_control_native import assert_close, random_inputs

N = 24
LEAK = 10.0


def _extra(n: int, seed: int) -> torch.Tensor:
    """A random extra rate [n, 6] (1/s): zero on some axes, and on arm 0 a rate that saturates the per-period clip."""
    gen = torch.Generator().manual_seed(seed)
    e = 40.0 * torch.rand(n, 6, generator=gen, dtype=torch.float64)
    e[torch.rand(n, 6, generator=gen) < 0.3] = 0.0
    e[0] = 2000.0  # Δt × rate > 1: the clip to one full relaxation per period
    return e


def _controller(backend: str, n: int = N, **options) -> A3CQPController:
    opts = ControllerOptions(backend=backend, leak_axes="per_axis", desired_state_leak=LEAK, **options)
    return A3CQPController(n, options=opts)


def _stepped(backend: str, inputs: dict, q_des: tuple, leak_extra: torch.Tensor | None):
    ctrl = _controller(backend)
    if backend == "native":
        assert ctrl._native is not None
    ctrl.reset(*q_des)
    out = ctrl.step(**inputs, leak_extra=leak_extra)
    return out, ctrl


def _inputs(seed: int = 11) -> tuple[dict, tuple]:
    inputs, _ = random_inputs(N, seed=seed)
    gen = torch.Generator().manual_seed(seed + 1)
    q_des = (inputs["q"] + 0.02 * torch.randn(N, 7, generator=gen, dtype=torch.float64),
             inputs["qd"] + 0.1 * torch.randn(N, 7, generator=gen, dtype=torch.float64))
    return inputs, q_des


def _by_hand(ctrl: A3CQPController, inputs: dict, q_des: tuple, qdd: np.ndarray, extra: np.ndarray) -> tuple:
    """q*, q̇* after eq. 6-7 and one relaxation at rate clip(Δt (leak (w2 + w3 min(1, f_d)) + extra)) per axis of L
    (the task-space part) and clip(Δt leak) in the null space, written out in plain numpy."""
    dt = ctrl.dt
    q, qd = inputs["q"].numpy(), inputs["qd"].numpy()
    qs0, qds0 = (t.numpy() for t in q_des)
    qds = qds0 + dt * qdd
    qs = qs0 + dt * qds0 + 0.5 * dt * dt * qdd
    J, R = inputs["kin"].jac.numpy(), inputs["kin"].rot.numpy()
    w = inputs["weights"].numpy()
    fd = np.clip(inputs["f_d"].numpy(), 0.0, 1.0)
    r = np.clip(dt * (LEAK * (w[..., 1] + w[..., 2] * fd) + extra), 0.0, 1.0)
    jpinv = np.swapaxes(J, 1, 2) @ np.linalg.inv(J @ np.swapaxes(J, 1, 2) + ctrl.options.nullspace_damping * np.eye(6))
    out = []
    for des, meas in ((qs, q), (qds, qd)):
        d = des - meas
        dx = np.einsum("nij,nj->ni", J, d)
        loc = np.concatenate([np.einsum("nji,nj->ni", R, dx[:, :3]), np.einsum("nji,nj->ni", R, dx[:, 3:])], 1) * r
        back = np.concatenate([np.einsum("nij,nj->ni", R, loc[:, :3]), np.einsum("nij,nj->ni", R, loc[:, 3:])], 1)
        task = np.einsum("nij,nj->ni", jpinv, dx)
        out.append(des - np.einsum("nij,nj->ni", jpinv, back) - min(dt * LEAK, 1.0) * (d - task))
    return out[0], out[1]


@pytest.mark.parametrize("backend", ["python", "native"])
def test_the_extra_rate_adds_to_the_per_axis_rate_in_one_relaxation(backend: str) -> None:
    if backend == "native" and native.load() is None:
        pytest.skip("no C compiler: the native step is not built")
    inputs, q_des = _inputs()
    extra = _extra(N, seed=2)
    out, ctrl = _stepped(backend, inputs, q_des, extra)
    assert out.status.eq(0).all()
    qs, qds = _by_hand(ctrl, inputs, q_des, out.qdd.numpy(), extra.numpy())
    assert_close(ctrl.q_des, qs, "q*", rtol=1e-12)
    assert_close(ctrl.qd_des, qds, "q̇*", rtol=1e-12)
    # and the extra rate does something: without it q* ends elsewhere
    plain, _ = _stepped(backend, inputs, q_des, None)
    moved = np.abs(ctrl.q_des.numpy() - _by_hand(ctrl, inputs, q_des, plain.qdd.numpy(), 0.0 * extra.numpy())[0])
    assert moved.max() > 1e-6


@pytest.mark.skipif(native.load() is None, reason="no C compiler: the native step is not built")
def test_native_and_python_agree_with_an_extra_rate() -> None:
    inputs, q_des = _inputs(seed=17)
    extra = _extra(N, seed=5)
    (a, pa), (b, pb) = (_stepped(be, inputs, q_des, extra) for be in ("python", "native"))
    for f in ("tau", "qdd", "wrench", "qdd_pd"):
        assert_close(getattr(b, f), getattr(a, f), f)
    assert_close(pb.q_des, pa.q_des, "q*")
    assert_close(pb.qd_des, pa.qd_des, "q̇*")


@pytest.mark.skipif(native.load() is None, reason="no C compiler: the native step is not built")
def test_native_and_python_closed_loops_agree_with_a_switching_extra_rate() -> None:
    n = 3
    gen = torch.Generator().manual_seed(4)
    sims = {be: PandaSim(n, control_site="tcp") for be in ("python", "native")}
    ctrls = {be: _controller(be, n) for be in ("python", "native")}
    s = sims["python"].observe()
    pos_d = s.kin.pos + 0.1 * (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5)
    rot_d = s.kin.rot.clone()
    for k in range(200):
        if k % 20 == 0:
            w = torch.softmax(3.0 * torch.randn(n, 6, 3, generator=gen, dtype=torch.float64), dim=-1)
            f_d = 2.0 * torch.rand(n, 6, generator=gen, dtype=torch.float64)
            extra = None if k % 40 == 0 else 20.0 * torch.rand(n, 6, generator=gen, dtype=torch.float64)
        outs = {}
        for be in ("python", "native"):
            s = sims[be].observe()
            outs[be] = ctrls[be].step(s.q, s.qd, s.mass, s.bias, w, f_d, pos_d, rot_d, f_env=s.f_env, kin=s.kin,
                                      leak_extra=extra)
            sims[be].step(outs[be].tau)
        for f in ("tau", "qdd", "wrench"):
            assert_close(getattr(outs["native"], f), getattr(outs["python"], f), f"step {k} {f}", rtol=1e-7)


@pytest.mark.parametrize("backend", ["python", "native"])
def test_no_extra_and_a_zero_extra_are_bit_identical(backend: str) -> None:
    if backend == "native" and native.load() is None:
        pytest.skip("no C compiler: the native step is not built")
    inputs, q_des = _inputs(seed=23)
    (a, pa), (b, pb) = (_stepped(backend, inputs, q_des, e) for e in (None, torch.zeros(N, 6, dtype=torch.float64)))
    assert torch.equal(pa.q_des, pb.q_des) and torch.equal(pa.qd_des, pb.qd_des)
    assert torch.equal(a.tau, b.tau)
    # and None is the per-axis leak alone, written out by hand
    qs, qds = _by_hand(pa, inputs, q_des, a.qdd.numpy(), np.zeros((N, 6)))
    assert_close(pa.q_des, qs, "q*", rtol=1e-12)
    assert_close(pa.qd_des, qds, "q̇*", rtol=1e-12)


def test_bad_extra_rates_are_refused_with_one_line() -> None:
    inputs, q_des = _inputs()
    ctrl = _controller("auto")
    ctrl.reset(*q_des)
    with pytest.raises(ControlShapeError, match=r"leak_extra must have shape \(24, 6\), got \(24, 3\)"):
        ctrl.step(**inputs, leak_extra=torch.zeros(N, 3))
    bad = torch.zeros(N, 6, dtype=torch.float64)
    bad[3, 2] = float("nan")
    with pytest.raises(InvalidGainError, match="leak_extra must be finite"):
        ctrl.step(**inputs, leak_extra=bad)
    bad[3, 2] = -0.5
    with pytest.raises(InvalidGainError, match="leak_extra must be ≥ 0.*-0.5"):
        ctrl.step(**inputs, leak_extra=bad)
    min_w1 = A3CQPController(N, options=ControllerOptions(leak_axes="min_w1"))
    with pytest.raises(InvalidGainError, match="leak_extra needs ControllerOptions.leak_axes 'per_axis'"):
        min_w1.step(**inputs, leak_extra=torch.zeros(N, 6, dtype=torch.float64))
    out = min_w1.step(**inputs)  # nothing was half-done: the next plain step runs
    assert out.status.eq(0).all()
