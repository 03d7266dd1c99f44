"""bench/point_mass_gym.py is the same task as envs.point_mass.PointMassEnv (the SB3 baseline's env).

Same episode parameters + same actions -> same x, ẋ, f_env, f_ope, w, f_d, reward to 1e-9 for every
step of a full episode, per scenario; same sampling of episodes from the same uniform draws; gymnasium
API conformance (check_env). Needs no Stable-Baselines3.
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


@pytest.mark.parametrize("scenario,random_init", [(s, True) for s in SCENARIOS] + [("wall_operator", False)])
def test_episode_sampling_matches_torchrl_env(scenario, random_init):
    """Same uniform draws -> same episode: order, ranges and construction of every drawn quantity."""
    cfg = one_scenario(scenario, random_initial_weights=random_init)
    tenv = PointMassEnv(1, cfg, seed=5)
    draws = []
    real_uniform = tenv._uniform

    def recording(n, lo, hi, *shape):
        out = real_uniform(n, lo, hi, *shape)
        draws.append((float(lo), float(hi), tuple(shape), out[0].numpy().copy()))
        return out

    tenv._uniform = recording
    tenv.reset()
    expected = torch_episode_params(tenv)

    replay = iter(draws)

    def uniform(lo, hi, shape):
        rlo, rhi, rshape, out = next(replay)
        assert (lo, hi, shape) == (rlo, rhi, rshape)
        return out

    genv = PointMassGym(cfg)
    genv.reset(seed=0)
    got = genv._sample_episode(uniform)
    # Every draw of the live episode consumed; what is left, if anything, is one more whole episode
    # drawn in advance by the TorchRL env (its pending next episode).
    left = len(list(replay))
    assert left in (0, len(draws) - left), (left, len(draws))
    assert got["scenario"] == expected["scenario"] == SCENARIOS.index(scenario)
    assert got["has_wall"] == expected["has_wall"]
    for k in ("target", "wall_pos", "f_d"):
        assert got[k] == pytest.approx(expected[k], abs=1e-12), k
    np.testing.assert_allclose(got["w_logits"], expected["w_logits"], rtol=0, atol=1e-12)
    np.testing.assert_array_equal(got["schedule"], expected["schedule"])
    if scenario in ("operator", "wall_operator"):
        assert np.count_nonzero(got["schedule"]) > 0


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


def test_sb3_trains_on_the_gym_env():
    """Smoke: the baseline's exact SB3 construction runs on PointMassGym (skipped without the bench extra)."""
    pytest.importorskip("stable_baselines3")
    rate, seconds = _train_speed().run_sb3(load_config(CONFIG), 64)
    assert rate > 0 and seconds > 0
