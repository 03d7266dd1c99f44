"""The control period's sensing in C (a3cqp_rl/robot/sense.py) against the numpy path it replaces."""

from __future__ import annotations

import copy

import numpy as np
import pytest
import torch

from a3cqp_rl.control import controller as controller_mod
from a3cqp_rl.control.controller import wrench_from_joint_torques
from a3cqp_rl.robot import PandaSim, sense
from a3cqp_rl.robot.mjcf import table_xml
from a3cqp_rl.robot.sim import ShardedPandaSim

OUTPUTS = ("_q", "_qd", "_mass", "_bias", "_ft", "_f_env", "_cs_pos", "_cs_rot", "_jt", "_twist", "_jdot_qdot")

needs_library = pytest.mark.skipif(sense._library.get() is None, reason="the native sensing library is not built")


def _both(sim: PandaSim, names: tuple[str, ...] = OUTPUTS) -> tuple[dict, dict]:
    """The observe() arrays after one mj_step1, from the C read-out and from the numpy one (the same state)."""
    native = sim._native_observe
    sim._observe_arrays()
    c = {k: getattr(sim, k).copy() for k in names}
    sim._native_observe = None
    try:
        sim._observe_arrays()  # mj_step1 again at the same state: the same MuJoCo arrays
    finally:
        sim._native_observe = native
    return c, {k: getattr(sim, k).copy() for k in names}


def _drive(sim, steps: int, seed: int) -> None:  # noqa: ANN001
    """Move the arms with random torques and random pushes below the F/T sensor (the tool tip), so that every
    quantity is nonzero: joint speeds, the sensor's reading, the environment wrench."""
    gen = np.random.default_rng(seed)
    for _ in range(steps):
        s = sim.observe()
        sim.push(gen.normal(0.0, 20.0, (sim.n, 3)), site="tcp", torque_world=gen.normal(0.0, 1.0, (sim.n, 3)))
        sim.step(s.bias.numpy() + gen.normal(0.0, 5.0, (sim.n, 7)))


@needs_library
@pytest.mark.parametrize("scene", ["", "table"])
def test_native_read_out_matches_the_numpy_one(scene: str) -> None:
    sim = PandaSim(3, tool="peg", scene=table_xml() if scene else "")
    assert sim._native_observe is not None
    _drive(sim, 60, seed=1)
    c, py = _both(sim)
    for k in OUTPUTS:
        scale = max(1.0, float(np.abs(py[k]).max()))
        np.testing.assert_allclose(c[k], py[k], rtol=0, atol=1e-12 * scale, err_msg=k)
    assert np.abs(py["_f_env"]).max() > 1.0 and np.abs(py["_twist"]).max() > 1e-3  # the check compares something


@needs_library
def test_native_read_out_of_a_sharded_sim_matches_the_numpy_one() -> None:
    sim = ShardedPandaSim(4, parts=2, tool="peg")
    _drive(sim, 40, seed=2)
    native = [p._native_observe for p in sim.parts]
    sim.observe()
    c = {k: getattr(sim, k).copy() for k in OUTPUTS}
    for p in sim.parts:
        p._native_observe = None
    try:
        sim.observe()
    finally:
        for p, fn in zip(sim.parts, native):
            p._native_observe = fn
    for k in OUTPUTS:
        scale = max(1.0, float(np.abs(getattr(sim, k)).max()))
        np.testing.assert_allclose(c[k], getattr(sim, k), rtol=0, atol=1e-12 * scale, err_msg=k)


def _random_inputs(n: int, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    gen = np.random.default_rng(seed)
    a = gen.normal(size=(n, 7, 7))
    mass = a @ a.transpose(0, 2, 1) + 0.1 * np.eye(7)
    jt = gen.normal(size=(n, 7, 12))  # J as PandaSim keeps it: the transposed view of [Jᵀ | J̇ᵀ]'s first half
    return gen.normal(size=(n, 7)) * 5.0, jt, mass


@needs_library
def test_native_wrench_matches_the_numpy_solves(monkeypatch) -> None:  # noqa: ANN001
    tau, jt, mass = _random_inputs(9, seed=3)
    tau[2] = 0.0  # nothing pushes this arm: exactly 0
    tau[5, 3] = np.nan  # a NaN reading propagates
    jac = jt[:, :, :6].transpose(0, 2, 1)  # strided, as SimState's
    args = torch.from_numpy(tau), torch.from_numpy(jac), torch.from_numpy(mass)
    c = wrench_from_joint_torques(*args).numpy()
    monkeypatch.setattr(controller_mod, "_native_wrench", lambda *a: None)
    py = wrench_from_joint_torques(*args).numpy()
    ok = np.isfinite(py).all(1)
    assert ok.tolist() == [True] * 5 + [False] + [True] * 3
    assert np.isnan(c[5]).all() and (c[2] == 0.0).all() and (py[2] == 0.0).all()
    np.testing.assert_allclose(c[ok], py[ok], rtol=1e-9, atol=1e-9)
    assert np.abs(py[ok]).max() > 1.0


@needs_library
def test_native_wrench_leaves_other_shapes_to_the_numpy_path() -> None:
    tau, jt, mass = _random_inputs(3, seed=8)
    jac = jt[:, :, :6].transpose(0, 2, 1)
    assert sense.wrench(tau, jac[:1], mass, 1e-6) is None  # a batch of one J for three arms: never read past it
    assert sense.wrench(tau[:, :6], jac, mass, 1e-6) is None
    expanded = torch.from_numpy(jac[:1].copy()).expand(3, 6, 7)  # stride 0 along the batch: read with its strides
    one = wrench_from_joint_torques(torch.from_numpy(tau), expanded, torch.from_numpy(mass)).numpy()
    np.testing.assert_allclose(one, sense.wrench(tau, np.repeat(jac[:1], 3, axis=0), mass, 1e-6), rtol=1e-9, atol=1e-9)


@needs_library
def test_native_wrench_says_nan_for_a_mass_matrix_that_is_not_positive_definite() -> None:
    tau, jt, mass = _random_inputs(2, seed=4)
    mass[1] = -mass[1]
    out = sense.wrench(tau, jt[:, :, :6].transpose(0, 2, 1), mass, 1e-6)
    assert np.isfinite(out[0]).all() and np.isnan(out[1]).all()


@needs_library
def test_a_copied_sim_reads_its_own_data() -> None:
    sim = PandaSim(2, tool="peg")
    _drive(sim, 20, seed=6)
    twin = copy.deepcopy(sim)
    q_seen, q_now = sim._q.copy(), sim.data.qpos[sim._qadr]
    twin.data.qpos[:] += 0.01  # the copy moves, the original does not
    s = twin.observe()
    assert twin._native_observe is not sim._native_observe
    np.testing.assert_array_equal(sim._q, q_seen)  # the copy's read-out did not write into the original's arrays
    np.testing.assert_allclose(s.q.numpy(), q_now + 0.01, atol=1e-12)
    np.testing.assert_allclose(sim.observe().q.numpy(), q_now, atol=1e-12)


def test_observe_returns_one_state_whose_tensors_follow_the_sim() -> None:
    """SimState is made once per sim (its tensors share the arrays the read-out writes in place): the next
    observe() returns it with the new step's numbers; a copy of the sim makes its own."""
    sim = PandaSim(2, tool="peg")
    s = sim.observe()
    q0 = s.q.clone()
    sim.step(s.bias.numpy() + 3.0)
    s2 = sim.observe()
    assert s2 is s and not torch.equal(s2.q, q0)
    np.testing.assert_array_equal(s2.q.numpy(), sim.data.qpos[sim._qadr])
    twin = copy.deepcopy(sim)
    t = twin.observe()
    assert t is not s and np.shares_memory(t.q.numpy(), twin._q) and not np.shares_memory(t.q.numpy(), sim._q)


@needs_library
def test_without_a_control_site_the_read_out_still_matches() -> None:
    sim = PandaSim(2, tool="peg", control_site=None)
    _drive(sim, 20, seed=7)
    c, py = _both(sim, OUTPUTS[:6])
    for k in OUTPUTS[:6]:
        np.testing.assert_allclose(c[k], py[k], rtol=0, atol=1e-12 * max(1.0, float(np.abs(py[k]).max())), err_msg=k)


def test_switched_off_the_numpy_read_out_runs(monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setenv("A3CQP_NATIVE_SENSE", "0")
    sense._library.reset()
    try:
        sim = PandaSim(2, tool="peg")
        assert sim._native_observe is None
        tau, jt, mass = _random_inputs(2, seed=5)
        assert sense.wrench(tau, jt[:, :, :6].transpose(0, 2, 1), mass, 1e-6) is None
        s = sim.observe()
        assert np.isfinite(s.mass.numpy()).all() and s.kin is not None
    finally:
        monkeypatch.delenv("A3CQP_NATIVE_SENSE")
        sense._library.reset()
