"""PopulationController: per-robot gains and strict levels in one batch equal one A3CQPController per robot."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from a3cqp_rl.config import ControllerConfig
from a3cqp_rl.control import A3CQPController, ControllerOptions
from a3cqp_rl.control.exceptions import InvalidGainError, InvalidLevelError
from a3cqp_rl.control.population import TASKS, PopulationController, RobotGains
from test_control_native import random_inputs

N = 12


@pytest.fixture(scope="module")
def states() -> tuple[dict, object]:
    return random_inputs(N, seed=3)


def _rows(inputs: dict, idx: list[int]) -> dict:
    out = {}
    for k, v in inputs.items():
        if k == "kin":
            out[k] = type(v)(**{f: getattr(v, f)[idx] for f in ("pos", "rot", "jac", "jdot_qdot", "twist")})
        else:
            out[k] = v[idx]
    return out


def _x(out) -> np.ndarray:  # noqa: ANN001
    return torch.cat([out.qdd, out.wrench, out.tau], 1).numpy()


def test_uniform_population_equals_the_controller(states) -> None:  # noqa: ANN001
    """Table I gains, every task in level 1: the same torques as A3CQPController (Python objects) to rounding."""
    inputs, model = states
    ref = A3CQPController(N, model=model, options=ControllerOptions(backend="python"))
    pop = PopulationController(N, model=model)
    for _ in range(3):  # a few steps: q*, q̇* integrate identically too
        a, b = ref.step(**inputs), pop.step(**inputs)
        np.testing.assert_allclose(_x(b), _x(a), rtol=0, atol=1e-9)
    assert str(pop.hierarchy) == "(" + " + ".join(TASKS) + ")"


def _random_population(seed: int) -> tuple[RobotGains, np.ndarray]:
    rng = np.random.default_rng(seed)
    gains = RobotGains(kp=rng.uniform(20, 600, N), k_theta=rng.uniform(5, 100, N), lambda_d=rng.uniform(1, 20, N),
                       c_d=rng.uniform(1, 30, N), kq=rng.uniform(1, 50, N), jc_weight=10 ** rng.uniform(-1, 1, N),
                       cartesian_regularization=10 ** rng.uniform(-3, -1, N))
    levels = rng.integers(0, 4, size=(N, len(TASKS)))
    levels[0] = 1  # one flat robot, one with a gap (levels 1 and 3), one with every task off
    levels[1] = [1, 3, 3, 0, 1]
    levels[2] = 0
    return gains, levels


def test_each_robot_equals_its_own_controller(states) -> None:  # noqa: ANN001
    """Robot b of a population with random gains and levels gets what A3CQPController(levels=its levels) with its
    gains computes for it alone (to the QP's tolerance)."""
    inputs, model = states
    gains, levels = _random_population(0)
    pop = PopulationController(N, model=model, gains=gains, levels=levels)
    out = pop.step(**inputs)
    assert not out.fallback.any()
    for b in range(N):
        cfg = ControllerConfig(kp=gains.kp[b], k_theta=gains.k_theta[b], lambda_d=gains.lambda_d[b], c_d=gains.c_d[b],
                               kq=gains.kq[b], epsilon=1e-4 * gains.jc_weight[b])
        opt = ControllerOptions(backend="python", jc_nullspace_weight=1e-3 * gains.jc_weight[b],
                                cartesian_regularization=gains.cartesian_regularization[b])
        lv = {name: int(levels[b, t]) or None for t, name in enumerate(TASKS)}
        one = A3CQPController(1, model=model, config=cfg, options=opt, levels=lv)
        sub = _rows(inputs, [b])
        for col, name in enumerate(("ik", "ac", "fc")):  # the population zeroes an off task's weights itself
            if lv[name] is None:
                sub["weights"] = sub["weights"].clone()
                sub["weights"][..., col] = 0.0
        ref = one.step(**sub)
        assert pop.describe(b) == str(one.hierarchy)
        np.testing.assert_allclose(_x(out)[b], _x(ref)[0], rtol=0, atol=2e-5 * (1 + np.abs(_x(ref)[0]).max()),
                                   err_msg=f"robot {b}: {pop.describe(b)}")


def test_weighted_sum_blend_equals_the_controller(states) -> None:  # noqa: ANN001
    """wrench_blend "weighted_sum" (the env's eq. 35 blend, IK's zero-wrench residual): one level per robot equals
    A3CQPController, and robots with strict levels still solve (IK's wrench residual goes in IK's level)."""
    inputs, model = states
    opt = ControllerOptions(backend="python", wrench_blend="weighted_sum", cartesian_regularization=1.0)
    ref = A3CQPController(N, model=model, options=opt)
    levels = np.ones((N, len(TASKS)), dtype=np.int64)
    pop = PopulationController(N, model=model, options=opt, levels=levels)
    np.testing.assert_allclose(_x(pop.step(**inputs)), _x(ref.step(**inputs)), rtol=0, atol=1e-9)
    levels[: N // 2] = [2, 1, 1, 3, 1]  # IK below AC and FC
    pop = PopulationController(N, model=model, options=opt, levels=levels)
    out = pop.step(**inputs)
    assert not out.fallback.any() and np.isfinite(_x(out)).all()


def test_levels_are_closed_up_and_validated() -> None:
    pop = PopulationController(2, levels=np.array([[1, 3, 3, 0, 1], [2, 2, 2, 2, 2]]))
    assert pop.robot_levels.tolist() == [[1, 2, 2, 0, 1], [1, 1, 1, 1, 1]]
    assert pop.level_count.tolist() == [2, 1]
    assert pop.describe(0) == "(ik + cartesian_regularizer) / (ac + fc); off: jc"
    with pytest.raises(InvalidLevelError, match="robot 1, task 'fc'"):
        pop.set_robot_levels(np.array([[1, 1, 1, 1, 1], [1, 1, 4, 1, 1]]))
    with pytest.raises(InvalidLevelError, match="shape"):
        pop.set_robot_levels(np.ones((3, 5), dtype=int))
    pop.set_levels({"ik": 1, "ac": 2, "fc": 2, "jc": 3, "cartesian_regularizer": None})
    assert pop.robot_levels.tolist() == [[1, 2, 2, 3, 0]] * 2


def test_gains_are_validated() -> None:
    g = RobotGains.uniform(3)
    with pytest.raises(InvalidGainError, match="gain lambda_d of robot 1"):
        PopulationController(3, gains=RobotGains(**{**g.__dict__, "lambda_d": np.array([1.0, 0.0, 1.0])}))
    with pytest.raises(InvalidGainError, match="one value per robot"):
        PopulationController(3, gains=RobotGains(**{**g.__dict__, "kp": np.ones(2)}))
    assert PopulationController(3, options=ControllerOptions(backend="native"))._native is not None


@pytest.mark.parametrize("blend", ["normalized", "weighted_sum"])
@pytest.mark.parametrize("strict", [False, True])
def test_native_population_equals_the_python_objects(states, blend: str, strict: bool) -> None:  # noqa: ANN001
    """The C step with random per-robot gains (and, `strict`, random levels: the cascade fed one C cost per level)
    computes the Python objects' torques to rounding, over a few steps (q*, q̇* integrate identically)."""
    inputs, model = states
    gains, levels = _random_population(7)
    if not strict:  # one level per robot, random tasks off
        levels = np.minimum(levels, 1)
        levels[0] = 1
    opt = ControllerOptions(wrench_blend=blend, cartesian_regularization=1.0 if blend == "weighted_sum" else 1e-2)
    ref = PopulationController(N, model=model, options=dataclasses.replace(opt, backend="python"), gains=gains,
                               levels=levels)
    pop = PopulationController(N, model=model, options=dataclasses.replace(opt, backend="native"), gains=gains,
                               levels=levels)
    assert pop._native is not None and ref._native is None
    for _ in range(3):
        a, b = ref.step(**inputs), pop.step(**inputs)
        assert not a.fallback.any()
        tol = 1e-9 if not strict else 1e-7  # the cascade's level tolerances amplify the assembly's rounding
        np.testing.assert_allclose(_x(b), _x(a), rtol=0, atol=tol * (1 + np.abs(_x(a)).max()))
        np.testing.assert_allclose(b.f_adm.numpy()[levels[:, 1] > 0], a.f_adm.numpy()[levels[:, 1] > 0], atol=1e-9)
    np.testing.assert_array_equal(pop.saturated_periods, ref.saturated_periods)


def test_native_population_refuses_replaced_tasks(states) -> None:  # noqa: ANN001
    """backend "native" with a population whose tasks were swapped after construction keeps to the objects."""
    inputs, model = states
    pop = PopulationController(N, model=model)
    assert pop._native is not None
    pop.tasks = list(pop.tasks)
    pop.tasks[0] = type(pop.tasks[0])(pop.gains.kp * 2, pop.gains.k_theta)
    out = pop.step(**inputs)  # the composition changed: the Python objects run (and agree with themselves)
    assert np.isfinite(_x(out)).all()


def test_native_robot_rows_are_checked(states) -> None:  # noqa: ANN001
    """The per-robot rows of the C step name every field once and have one row per arm."""
    _, model = states
    pop = PopulationController(N, model=model)
    step = pop._native
    with pytest.raises(ValueError, match="missing or unknown"):
        step.robot_rows(kp=np.ones((N, 6)))
    rows = pop._robot_rows[0]
    assert rows.shape == (N, step.lib.a3cqp_robot_size())
    inputs, _ = states
    with pytest.raises(ValueError, match="per-robot rows must have shape"):
        pop.step(**inputs)  # fills q*, q̇*
        step.assemble(robots=rows[:-1], packed=np.zeros((N, step.lib.a3cqp_input_size())))


def test_a_fallback_starts_only_the_failed_robots_levels_cold(states, monkeypatch) -> None:  # noqa: ANN001
    """Robots in groups of different level counts: the one that fails has its multipliers dropped in its group's
    warm starts (at its place within the group); every other robot keeps its own."""
    import a3cqp_rl.control.population as population_module
    from a3cqp_rl.control.hierarchy import solve_cascade
    from a3cqp_rl.qp import QPStatus

    inputs, model = random_inputs(N, seed=8, near_limits=True)
    gains, levels = _random_population(0)
    pop = PopulationController(N, model=model, gains=gains, levels=levels)
    failing = 5
    k_fail, idx_fail = next((k, idx) for k, idx in pop._groups if failing in idx.tolist())
    kept = {}

    def robot_fails(costs, G, h, *a, **kw):  # noqa: ANN001, ANN202
        sol = solve_cascade(costs, G, h, *a, **kw)
        k = len(costs)
        kept[k] = [torch.cat([s.z, s.z_lb, s.z_ub], 1).clone() for s in sol.solutions]
        if k == k_fail:
            sol.status[idx_fail.tolist().index(failing)] = QPStatus.MAX_ITER
        return sol

    monkeypatch.setattr(population_module, "solve_cascade", robot_fails)
    out = pop.step(**inputs)
    assert out.fallback.tolist() == [b == failing for b in range(N)]
    row_fail = idx_fail.tolist().index(failing)
    assert len(pop._groups) > 1 and any(bool((d[row_fail] > 0).any()) for d in kept[k_fail])
    for k, idx in pop._groups:
        for sol, before in zip(pop._warm_groups[k], kept[k]):
            now = torch.cat([sol.z, sol.z_lb, sol.z_ub], 1)
            for row, b in enumerate(idx.tolist()):
                assert torch.equal(now[row], torch.zeros_like(now[row]) if b == failing else before[row]), (k, b)
