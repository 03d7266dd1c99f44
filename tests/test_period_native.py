"""PandaEnv's control-period arithmetic in C (envs/native/period.py) against the numpy path it replaces."""

from __future__ import annotations

import contextlib
import logging

import numpy as np
import pytest
import torch

from a3cqp_rl.config import config_from_dict
from a3cqp_rl.robot import PANDA_LIMITS
from a3cqp_rl.robot.sim import cross3
from envs.native import period as period_mod
from envs.panda import PandaEnv
from envs.scenarios import rotvec_to_matrix

needs_library = pytest.mark.skipif(period_mod._library.get() is None, reason="the native period library is not built")

FAST_PEG = {"panda": {"peg_in_hole": {"settle_time": 0.1, "approach_time": 1.0, "align_time": 3.0,
                                      "time_limit": 6.0}}}


def _native(n: int) -> period_mod.NativePeriod:
    lim = PANDA_LIMITS
    return period_mod.native_period(n, dq_max=np.array(lim.dq_max), q_lo=np.array(lim.q_min),
                                    q_hi=np.array(lim.q_max), speed_factor=3.0, penetration=0.01,
                                    o_ft=np.array([0.0, 0.01, -0.1]), o_handle=np.array([0.02, 0.0, -0.15]))


@needs_library
@pytest.mark.parametrize("distinct_truth", [False, True])
def test_native_measure_matches_the_numpy_tail(distinct_truth: bool) -> None:
    gen = np.random.default_rng(0)
    n = 7
    native = _native(n)
    o_ft, o_handle = native._keep[3], native._keep[4]
    pos, rot = gen.normal(0.0, 0.5, (n, 3)), rotvec_to_matrix(gen.normal(0.0, 1.0, (n, 3)))
    ft, f_ext = gen.normal(0.0, 10.0, (n, 6)), gen.normal(0.0, 10.0, (n, 6))
    truth = ft + gen.normal(0.0, 0.5, (n, 6)) if distinct_truth else ft
    # the numpy tail of PandaEnv._measure
    lever = rot @ o_ft
    ft_py, truth_py = ft.copy(), truth.copy()
    ft_py[:, 3:] += cross3(lever, ft_py[:, :3])
    truth_py[:, 3:] += cross3(lever, truth_py[:, :3])
    r_py = rot @ o_handle
    f_c, t_c = ft.copy(), (truth.copy() if distinct_truth else None)
    f_ope, r, hp = native.measure(pos, np.ascontiguousarray(rot), f_c, t_c, f_ext)
    np.testing.assert_allclose(f_c, ft_py, rtol=0, atol=1e-13)
    if distinct_truth:
        np.testing.assert_allclose(t_c, truth_py, rtol=0, atol=1e-13)
    np.testing.assert_allclose(f_ope, f_ext - ft_py, rtol=0, atol=1e-13)
    np.testing.assert_allclose(r, r_py, rtol=0, atol=1e-15)
    np.testing.assert_allclose(hp, pos + r_py, rtol=0, atol=1e-15)
    assert np.abs(f_c[:, 3:] - ft[:, 3:]).max() > 0.1  # the moment moved


def _states(env: PandaEnv, gen: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """q, q̇ [N, 7] and penetrations [N] (m) near and past every limit, with NaN and inf rows."""
    n = env.num_envs
    lo, hi = env._q_lo, env._q_hi
    q = gen.uniform(lo - 0.02, hi + 0.02, (n, 7))
    qd = gen.uniform(-1.2, 1.2, (n, 7)) * env._dq_max * gen.choice([1.0, 3.0], (n, 1))
    pen = gen.choice([0.0, 1e-3, 0.02], n)
    q[1, 3], qd[2, 5], q[3, 0], qd[4] = np.nan, np.inf, -np.inf, np.nan
    q[5] = np.array(hi) + 0.01  # equal excesses: the first joint
    return q, qd, pen


@needs_library
def test_native_checks_match_the_numpy_checks(caplog) -> None:  # noqa: ANN001
    gen = np.random.default_rng(1)
    cfg = config_from_dict(FAST_PEG)
    envs = [PandaEnv(12, cfg, seed=0)]
    with period_mod.numpy_period():
        envs.append(PandaEnv(12, cfg, seed=0))
    c, py = envs
    assert c._period is not None and py._period is None
    for env in envs:
        env.parked[6] = env.diverged[7] = True
    seen = set()
    for step in range(6):
        q, qd, pen = _states(c, gen)
        live = gen.random(12) < 0.8
        out = []
        for env in envs:
            env.q, env.qd = q.copy(), qd.copy()
            env.sim.max_penetration = lambda pen=pen: pen.copy()
            env._in_episode = lambda live=live: live.copy()
            caplog.clear()
            with caplog.at_level(logging.WARNING, logger="envs.panda"):
                if env is c:
                    bad = c._native_checks(live)
                else:
                    bad = py._check_divergence(np.abs(py.qd))
                    py._track_joint_limits(live, np.abs(py.qd))
            out.append((bad, [r.getMessage() for r in caplog.records]))
        (bad_c, log_c), (bad_py, log_py) = out
        np.testing.assert_array_equal(bad_c, bad_py)
        assert log_c == log_py
        seen.update(m.split("(")[1].split(" ")[0] for m in log_py)
        for name in ("max_penetration", "joint_limit_excess", "joint_limit_joint", "joint_speed_ratio"):
            np.testing.assert_array_equal(getattr(c, name), getattr(py, name), err_msg=name)
    assert seen == {"non-finite", "joint", "contact"}  # every kind of divergence was compared
    assert (c.joint_limit_excess[np.isfinite(c.joint_limit_excess)] > 0).any()


@needs_library
def test_a_peg_env_with_the_native_period_follows_the_numpy_one() -> None:
    """1.5 s of the peg scene (approach under IK), either period: the same trajectories and records to round-off."""
    cfg = config_from_dict(FAST_PEG)
    runs = []
    for native in (True, False):
        with contextlib.nullcontext() if native else period_mod.numpy_period():
            env = PandaEnv(2, cfg, seed=4)
        assert (env._period is not None) == native
        td = env.reset()
        pos = []
        for _ in range(150):
            td["action"] = torch.tensor([1.0, -1.0, -1.0, -1.0]).expand(2, 6, 4).clone()
            td = env.step(td)["next"]
            pos.append(env.pos.copy())
        runs.append((np.array(pos), env.handle_pos.copy(), env.f_ope.copy(), env.joint_speed_ratio.copy(),
                     env.joint_limit_excess.copy()))
    for a, b in zip(*runs):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-9)
    assert np.abs(runs[0][0][-1] - runs[0][0][0]).max() > 0.05 and (runs[0][3] > 0.01).all()


def test_switched_off_the_env_takes_the_numpy_period(monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.setenv("A3CQP_NATIVE_PERIOD", "0")
    period_mod._library.reset()
    try:
        assert _native_or_none() is None
        assert PandaEnv(1, config_from_dict(FAST_PEG), seed=0)._period is None
    finally:
        monkeypatch.delenv("A3CQP_NATIVE_PERIOD")
        period_mod._library.reset()


def _native_or_none() -> period_mod.NativePeriod | None:
    lim = PANDA_LIMITS
    return period_mod.native_period(1, dq_max=np.array(lim.dq_max), q_lo=np.array(lim.q_min), q_hi=np.array(lim.q_max),
                                    speed_factor=3.0, penetration=0.01, o_ft=np.zeros(3), o_handle=np.zeros(3))
