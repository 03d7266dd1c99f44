"""bench/point_mass_gym.py is the same task as envs.point_mass.PointMassEnv (the SB3 baseline's env).

Same episode parameters + same actions -> same x, ẋ, f_env, f_ope, w, f_d, reward to 1e-9 for every
step of a full episode, per scenario (the C point mass against the torch env); episodes drawn by the torch env;
gymnasium API conformance (check_env). Needs no Stable-Baselines3.
"""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from gymnasium.utils.env_checker import check_env

from a3cqp_rl.config import config_from_dict, load_config
from envs.point_mass import SCENARIOS, PointMassEnv, agent_step, observe_state

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "bench"))
from point_mass_gym import PointMassGym  # noqa: E402

CONFIG = Path(__file__).resolve().parents[1] / "configs" / "point_mass_a2c.yaml"
TOL = 1e-9


def one_scenario(scenario: str, **pm):
    return config_from_dict({"point_mass": {"scenario_probs": {scenario: 1.0}, **pm}})


def torch_episode_params(env: PointMassEnv) -> dict:
    """The live episode of PointMassEnv(1) in the form PointMassGym.reset(options=...) takes."""
    s, sched = env.functional()
    # schedule [N, T+1], or [2, N, T+1] double-buffered with the live slot in state["slot"]
    live = sched[int(s["slot"][0]), 0] if sched.dim() == 3 else sched[0]
    return {
        "scenario": int(s["scenario"][0]), "target": float(s["target"][0]), "wall_pos": float(s["wall_pos"][0]),
        "has_wall": bool(s["has_wall"][0]), "w_logits": s["w_logits"][0].numpy().copy(),
        "f_d": float(s["f_d"][0]), "schedule": live.numpy().copy(),
    }


def actions(steps: int, seed: int) -> np.ndarray:
    # Beyond [-1, 1] on purpose: both envs clip rates (eq. 29).
    return np.random.default_rng(seed).uniform(-1.2, 1.2, size=(steps, 4)).astype(np.float32)


@pytest.mark.parametrize("scenario", SCENARIOS)
def test_same_trajectory_as_torchrl_env_functional_step(scenario):
    cfg = one_scenario(scenario)
    tenv = PointMassEnv(1, cfg, seed=7)
    td0 = tenv.reset()
    genv = PointMassGym(cfg)
    obs, _ = genv.reset(seed=0, options=torch_episode_params(tenv))
    state, sched = tenv.functional()
    np.testing.assert_allclose(obs, td0["observation"][0].numpy(), rtol=0, atol=1e-7)
    steps = 300  # enough for contact and the first push; the full episode + truncation: next test
    keys = ("x", "x_dot", "f_env", "f_ope", "f_d")
    ref = {k: [] for k in (*keys, "w", "r", "obs")}
    got = {k: [] for k in (*keys, "w", "r", "obs")}
    for a in actions(steps, seed=SCENARIOS.index(scenario)):
        state, r_t = agent_step(state, torch.from_numpy(a).unsqueeze(0).to(torch.float64), sched,
                                tenv.cfg, tenv.adapt, tenv.rew)
        obs, r_g, terminated, truncated, info = genv.step(a)
        assert not terminated and not truncated
        for k in keys:
            ref[k].append(state[k][0])
            got[k].append(info[k])
        ref["w"].append(torch.softmax(state["w_logits"][0], -1))
        got["w"].append(genv.weights)
        ref["r"].append(r_t[0])
        got["r"].append(r_g)
        ref["obs"].append(observe_state(state, tenv.adapt)[0].to(torch.float32))
        got["obs"].append(obs)
    for k in ref:
        r_k, g_k = torch.stack(ref[k]).numpy(), np.asarray(got[k])
        assert r_k.shape == g_k.shape, k
        np.testing.assert_allclose(g_k, r_k, rtol=0, atol=1e-6 if k == "obs" else TOL, err_msg=k)
    trace = {k: np.asarray(got[k]) for k in ("f_env", "f_ope")}
    # The scenario's physics was actually exercised.
    if scenario in ("wall", "wall_operator"):
        assert min(trace["f_env"]) < -1.0
    else:
        assert max(np.abs(trace["f_env"])) == 0.0
    if scenario in ("operator", "wall_operator"):
        assert max(np.abs(trace["f_ope"])) > 1.0
    else:
        assert max(np.abs(trace["f_ope"])) == 0.0


def test_same_episode_through_torchrl_step_api_and_truncation():
    """Through PointMassEnv.step (float32 obs/reward, done flags), the paper config file with shorter episodes."""
    cfg = load_config(CONFIG, overrides={"point_mass": {"episode_steps": 150}})  # TorchRL steps cost ~1 ms
    cfg.point_mass.scenario_probs = {"wall_operator": 1.0}
    tenv = PointMassEnv(1, cfg, seed=3)
    td = tenv.reset()
    genv = PointMassGym(cfg)
    obs, _ = genv.reset(options=torch_episode_params(tenv))
    np.testing.assert_allclose(obs, td["observation"][0].numpy(), rtol=0, atol=1e-7)
    T = cfg.point_mass.episode_steps
    for i, a in enumerate(actions(T, seed=11)):
        td = tenv.step(td.set("action", torch.from_numpy(a).unsqueeze(0)))["next"]
        obs, r, terminated, truncated, info = genv.step(a)
        for k in ("x", "f_env", "f_ope"):
            assert abs(info[k] - float(td[k][0])) <= TOL, (i, k)
        np.testing.assert_allclose(obs, td["observation"][0].numpy(), rtol=0, atol=1e-6)
        assert abs(r - float(td["reward"][0, 0])) <= 1e-5 * max(1.0, abs(r))
        assert terminated == bool(td["terminated"][0, 0]) is False
        assert truncated == bool(td["truncated"][0, 0]) == (i == T - 1)


def test_episodes_come_from_the_torch_env_and_follow_the_seed():
    """The gym draws no episodes of its own: a seeded PointMassEnv(1) does; same seed, same episodes."""
    cfg = one_scenario("wall_operator")

    def episodes(seed):
        env = PointMassGym(cfg)
        first = env.reset(seed=seed)[1]
        return [env.episode_params() for _ in range(3) if env.reset() is not None], first

    (a, _), (b, _), (c, _) = episodes(4), episodes(4), episodes(5)
    for pa, pb in zip(a, b):
        assert pa["target"] == pb["target"] and np.array_equal(pa["schedule"], pb["schedule"])
    assert a[0]["target"] != c[0]["target"]
    assert all(p["scenario"] == 3 and p["has_wall"] and np.count_nonzero(p["schedule"]) > 0 for p in a)
    assert PointMassGym(cfg)._sampler is None  # drawn lazily, at the first reset


def test_torch_fallback_gives_the_same_trajectory(monkeypatch):
    """Without the C library the gym steps the torch env's agent_step: same numbers."""
    from envs import native

    cfg = one_scenario("wall_operator")
    fast = PointMassGym(cfg)
    monkeypatch.setattr(native, "load", lambda: None)
    slow = PointMassGym(cfg)
    assert fast._native is not None and slow._native is None
    p = (fast.reset(seed=2), fast.episode_params())[1]
    slow.reset(options=p)
    for a in actions(200, seed=3):
        o1, r1, _, t1, i1 = fast.step(a)
        o2, r2, _, t2, i2 = slow.step(a)
        assert abs(r1 - r2) <= 1e-9 and t1 == t2 and np.abs(o1 - o2).max() <= 1e-6
        assert all(abs(i1[k] - i2[k]) <= TOL for k in ("x", "x_dot", "f_env", "f_ope", "f_d"))
    np.testing.assert_allclose(fast.weights, slow.weights, rtol=0, atol=TOL)


def test_paper_episode_length_and_truncation():
    cfg = load_config(CONFIG)
    env = PointMassGym(cfg)
    env.reset(seed=0)
    T = cfg.point_mass.episode_steps
    assert T == PointMassEnv(1, cfg).cfg.episode_steps == 500
    flags = [env.step(env.action_space.sample())[2:4] for _ in range(T)]
    assert flags[-1] == (False, True) and all(f == (False, False) for f in flags[:-1])
    obs, _ = env.reset()  # a fresh episode starts at t = 0
    assert env.t == 0 and env.x == 0.0


def test_scenario_frequencies_follow_config():
    genv = PointMassGym(config_from_dict({"point_mass": {"scenario_probs": {"free": 0.25, "wall": 0.75}}}))
    genv.reset(seed=1)
    counts = np.bincount([genv.reset()[1]["scenario"] for _ in range(400)], minlength=4)
    assert counts[1] == counts[3] == 0
    assert 0.65 < counts[2] / 400 < 0.85


def test_gymnasium_api_and_reset_options():
    env = PointMassGym()
    check_env(env, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert env.observation_space.contains(obs) and obs.dtype == np.float32
    p = env.episode_params()
    env.reset(seed=123)
    env.reset(options=p)
    assert env.episode_params()["target"] == p["target"]
    np.testing.assert_array_equal(env.episode_params()["schedule"], p["schedule"])
    env.reset(options={"scenario": "free", "target": 0.3})
    assert env.scenario == 0 and not env.has_wall and env.target == 0.3
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(options={"targt": 0.1})
    with pytest.raises(ValueError, match="schedule"):
        env.reset(options={"schedule": np.zeros(3)})
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        env.step(np.array([np.nan, 0, 0, 0], dtype=np.float32))


def _train_speed():
    import train_speed  # bench/ is on sys.path (above)

    return train_speed


def test_train_speed_without_sb3_prints_how_to_install_and_exits_0(monkeypatch, capsys):
    monkeypatch.setitem(sys.modules, "stable_baselines3", None)  # import raises ImportError
    assert _train_speed().main(["--quick"]) == 0
    out = capsys.readouterr().out
    assert "stable-baselines3 is not installed" in out and "pip install" in out


def test_sb3_trains_on_the_gym_env(monkeypatch, tmp_path):
    """Smoke: the baseline's exact SB3 construction runs on PointMassGym and leaves no log folder behind (skipped
    without the bench extra)."""
    pytest.importorskip("stable_baselines3")
    logdir = tmp_path / "sb3_logs"
    monkeypatch.setenv("SB3_LOGDIR", str(logdir))  # where SB3's default logger would make its folder
    rate, seconds = _train_speed().run_sb3(load_config(CONFIG), 64)
    assert rate > 0 and seconds > 0
    assert not logdir.exists()
