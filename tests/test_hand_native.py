"""The operator's hand in C (envs/native/hand.py) against the numpy Operator.wrench and PandaSim.push it replaces."""

from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import pytest
import torch

from a3cqp_rl.config import OperatorConfig, config_from_dict
from a3cqp_rl.control.frames import rotation_log
from a3cqp_rl.robot import PandaSim
from a3cqp_rl.robot.sim import cross3
from envs.native import hand as hand_mod
from envs.panda import PandaEnv
from envs.scenarios import Operator, rotvec_to_matrix

needs_library = pytest.mark.skipif(hand_mod._library.get() is None, reason="the native hand library is not built")


def _operators(n: int, cfg: OperatorConfig, seed: int) -> tuple[Operator, Operator]:
    """Two operators in the same random state: hands idle, holding (mid-grip) and releasing, random goals."""
    gen = np.random.default_rng(seed)
    state = gen.integers(0, 3, n)
    state[:3] = (0, 1, 2)
    draws = dict(state=state, t_grasp=gen.uniform(0.0, 0.3, n), t_release=gen.uniform(0.0, 0.3, n),
                 start=gen.normal(0.0, 0.3, (n, 3)), goal=gen.normal(0.0, 0.3, (n, 3)),
                 rot_grasp=rotvec_to_matrix(gen.normal(0.0, 0.5, (n, 3))), force_scale=gen.uniform(0.7, 1.3, n))
    ops = (Operator(n, cfg, 1e-3), Operator(n, cfg, 1e-3))
    for op in ops:
        for name, value in draws.items():
            getattr(op, name)[:] = value
    return ops


def _handle_states(n: int, steps: int, seed: int) -> list[tuple[np.ndarray, ...]]:
    """Per control period: t [n], position [n, 3], the tip's twist [n, 6], the handle from the tip [n, 3], its
    rotation [n, 3, 3] and tremor draws [n, 1, 3]."""
    gen = np.random.default_rng(seed)
    out = []
    for k in range(steps):
        rot = rotvec_to_matrix(gen.normal(0.0, 0.6, (n, 3)))
        out.append((np.full(n, 0.05 + 1e-3 * k), gen.normal(0.0, 0.3, (n, 3)), gen.normal(0.0, 0.5, (n, 6)),
                    gen.normal(0.0, 0.1, (n, 3)), rot, gen.normal(size=(n, 1, 3))))
    return out


@needs_library
@pytest.mark.parametrize("intrinsic", [0.0, 25.0])
def test_native_wrench_matches_the_numpy_operator(intrinsic: float) -> None:
    n = 9
    cfg = dataclasses.replace(OperatorConfig(), intrinsic_damping=intrinsic, delay=0.004)
    py, c = _operators(n, cfg, seed=3)
    native = hand_mod.native_hand(c, None)
    assert native is not None and not native.pushes
    force, torque = np.zeros((n, 3)), np.zeros((n, 3))
    big = 0
    for t, pos, twist, r, rot, noise in _handle_states(n, 12, seed=4):  # 12 periods: the 4-slot history wraps
        v, w = twist[:, :3], twist[:, 3:]
        f_py, tq_py = py.wrench(t, pos, v + cross3(w, r), rot, w, noise[:, 0])
        native(t, 0.0, pos, twist, r, rot, noise, 0, force, torque)
        np.testing.assert_allclose(force, f_py, rtol=0, atol=1e-12)
        np.testing.assert_allclose(torque, tq_py, rtol=0, atol=1e-12)
        assert not force[py.state == 0].any()
        big += int((np.linalg.norm(f_py, axis=1) > 1.0).sum())
    assert big > n  # the hands hold and pull: the comparison is not of zeros
    assert c._k == py._k and np.array_equal(c._primed, py._primed)
    np.testing.assert_array_equal(c._hist, py._hist)


@needs_library
def test_native_rotation_log_of_the_grip_matches_near_zero_and_large_angles() -> None:
    """The rotational spring at a grip error of ~0 (the θ/sin θ series) and near π agrees with frames.rotation_log."""
    n = 4
    cfg = dataclasses.replace(OperatorConfig(), delay=1e-3, max_torque=1e6, rot_damping=0.0)
    py, c = _operators(n, cfg, seed=5)
    for op in (py, c):
        op.state[:] = 1
        op.t_grasp[:] = -1.0  # full grip
    angles = np.array([[1e-11, 0, 0], [0, 2e-9, 1e-9], [0, 0, 1.0], [3.1, 0.2, 0.0]])
    rot = np.ascontiguousarray(np.swapaxes(rotvec_to_matrix(angles), 1, 2) @ py.rot_grasp)  # R_grasp Rᵀ = exp(angles)
    pos, twist, r = np.zeros((n, 3)), np.zeros((n, 6)), np.zeros((n, 3))
    _, tq_py = py.wrench(np.zeros(n), pos, np.zeros((n, 3)), rot, np.zeros((n, 3)))
    force, torque = np.zeros((n, 3)), np.zeros((n, 3))
    hand_mod.native_hand(c, None)(np.zeros(n), 0.0, pos, twist, r, rot, None, 0, force, torque)
    # (the 3 × 3 products round differently: ~1e-16 in the grip error's entries, a tiny angle's torque moves by that)
    np.testing.assert_allclose(torque, tq_py, rtol=1e-12, atol=1e-14)
    expected = 3.0 * py.force_scale * np.linalg.norm(angles, axis=1)  # the spring's torque at the grip error
    np.testing.assert_allclose(np.linalg.norm(torque, axis=1), expected, rtol=1e-6, atol=1e-15)


@needs_library
def test_native_push_matches_the_numpy_push() -> None:
    """xfrc_applied and the pushes' joint torques (tau_ext after mj_step2) as PandaSim.push makes them."""
    gen = np.random.default_rng(6)
    sims = [PandaSim(3, tool="peg") for _ in range(2)]
    q = np.array(sims[0]._q) + gen.normal(0.0, 0.2, (3, 7))
    force = np.ascontiguousarray(gen.normal(0.0, 10.0, (3, 3)))
    torque = np.ascontiguousarray(gen.normal(0.0, 1.0, (3, 3)))
    force[1] = torque[1] = 0.0  # an arm no hand pushes
    for sim in sims:
        sim.reset(q)
        sim.observe()
    sims[0].push(force, site="handle", torque_world=torque)
    native = hand_mod.native_hand(Operator(3, OperatorConfig(), 1e-3), sims[1])
    assert native.pushes and native.push(force, torque)
    np.testing.assert_allclose(sims[1].data.xfrc_applied, sims[0].data.xfrc_applied, rtol=0, atol=1e-12)
    np.testing.assert_allclose(sims[1]._tau_push, sims[0]._tau_push, rtol=0, atol=1e-12)
    assert np.abs(sims[0]._tau_push).max() > 0.1 and not sims[0]._tau_push[1].any()
    tau = np.zeros((3, 7))
    for sim in sims:
        sim.step(tau)
    np.testing.assert_allclose(sims[1]._tau_ext, sims[0]._tau_ext, rtol=0, atol=1e-9)
    assert not native.push(np.zeros((3, 3)), np.zeros((3, 3)))


@needs_library
@pytest.mark.parametrize("threads", [1, 2])
def test_an_env_with_the_native_hand_follows_the_numpy_one(threads: int) -> None:
    """Guidance (the operator pulls every arm around, with tremor): 1.2 s of the env with either hand, the same
    trajectories to round-off; with two MuJoCo models (ShardedPandaSim) the parts push the C hand's wrench."""
    cfg = config_from_dict({"panda": {"guidance": {"pause": 0.2}}})
    runs = []
    for native in (True, False):
        with contextlib.nullcontext() if native else hand_mod.numpy_hand():
            env = PandaEnv(2, cfg, seed=11, scene="guidance", sim_threads=threads)
        assert (env._hand is not None) == native and (not native or env._hand.pushes == (threads == 1))
        td = env.reset()
        pos, held = [], 0
        for _ in range(120):
            td["action"] = torch.tensor([1.0, -1.0, -1.0, -1.0]).expand(2, 6, 4).clone()  # IK on (eq. 27 rates)
            td = env.step(td)["next"]
            pos.append(env.pos.copy())
            held += int(env.operator.active.sum())
        runs.append((np.array(pos), env.f_ope.copy(), held))
    (p_c, f_c, held_c), (p_py, f_py, held_py) = runs
    assert held_c == held_py > 50 and np.abs(p_py[-1] - p_py[0]).max() > 2e-3  # the hands moved the arms
    np.testing.assert_allclose(p_c, p_py, rtol=0, atol=1e-9)
    np.testing.assert_allclose(f_c, f_py, rtol=0, atol=1e-6)


def test_switched_off_the_env_takes_the_numpy_hand(monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setenv("A3CQP_NATIVE_HAND", "0")
    hand_mod._library.reset()
    try:
        assert hand_mod.native_hand(Operator(2, OperatorConfig(), 1e-3), None) is None
        assert PandaEnv(1, config_from_dict({}), seed=0, scene="guidance")._hand is None
    finally:
        monkeypatch.delenv("A3CQP_NATIVE_HAND")
        hand_mod._library.reset()
