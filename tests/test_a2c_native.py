"""The C A2C iteration (algorithms/native) against the torch reference `fused_iteration`."""

from __future__ import annotations

import pytest
import torch

from a3cqp_rl.config import config_from_dict
from algorithms import native
from algorithms.a2c import FusedRollout, ParamLayout, fused_iteration, train
from envs.point_mass import PointMassEnv

pytestmark = pytest.mark.skipif(native.load() is None, reason="no C compiler: the torch path runs (warned)")

CASES = {
    "paper": {},
    "privileged_gae_normalized_bound_deep": {"a2c": {"critic": "privileged", "gae_lambda": 0.9, "bound_coef": 1.0,
                                                     "normalize_advantage": True, "hidden": [16, 8, 12],
                                                     "learning_rate": 1e-2, "num_envs": 8, "n_steps": 5},
                                             "point_mass": {"operator_model": "drag"}},
    "shared_entropy": {"a2c": {"network": "shared", "ent_coef": 0.01, "learning_rate": 1e-2, "num_envs": 3,
                               "n_steps": 7, "max_grad_norm": 0.5}, "point_mass": {"operator_grip": True}},
}


def _setup(overrides: dict):
    cfg = config_from_dict({**overrides, "point_mass": {**overrides.get("point_mass", {}), "episode_steps": 13,
                                                        "scenario_probs": {"free": 0.2, "operator": 0.3, "wall": 0.3,
                                                                           "wall_operator": 0.2}}})
    hp = cfg.a2c
    env = PointMassEnv(hp.num_envs, cfg, seed=3)
    env.reset()
    step_fn, obs_fn = env.fused_functions(privileged=hp.critic == "privileged")
    layout = ParamLayout(3, 4, hp.hidden, hp.network, obs_fn(env.fused_inputs()[0]).shape[-1])
    return cfg, hp, env, step_fn, obs_fn, layout


@pytest.mark.parametrize("case", list(CASES))
def test_c_iteration_equals_the_torch_iteration(case):
    """60 iterations in lockstep (both start each one from the same state): state, reward, parameters, metrics."""
    cfg, hp, env, step_fn, obs_fn, layout = _setup(CASES[case])
    gen = torch.Generator().manual_seed(1)
    flat = layout.init(gen)
    flat += 0.05 * torch.randn(flat.shape, generator=gen)  # away from the init's symmetric zeros
    sq = torch.zeros_like(flat)
    it = native.NativeIteration(native.load(), env, layout, hp)
    worst = dict.fromkeys(("state", "reward", "flat", "sq", "metrics"), 0.0)
    ends = 0
    for _ in range(60):
        noise = torch.randn(hp.n_steps, hp.num_envs, 4, generator=gen)
        state, pending, schedule = env.fused_inputs()
        ref_state = {k: v.clone() for k, v in state.items()}
        ref_flat, ref_sq = flat.clone(), sq.clone()
        ref_state, ref_m, ref_r, ref_d = fused_iteration(layout, hp, step_fn, obs_fn, ref_flat, ref_sq, ref_state,
                                                         pending, schedule, noise)
        state, m, r, d = it(flat, sq, state, pending, schedule, noise)
        assert torch.equal(d, ref_d.bool()) and it.done_count == int(d.sum())
        ends += int(d.sum())
        for k in state:
            assert state[k].dtype == ref_state[k].dtype
            worst["state"] = max(worst["state"], (state[k].double() - ref_state[k].double()).abs().max().item())
        worst["reward"] = max(worst["reward"], (r - ref_r).abs().max().item())
        worst["flat"] = max(worst["flat"], (flat - ref_flat).abs().max().item())
        worst["sq"] = max(worst["sq"], ((sq - ref_sq).abs() / (ref_sq.abs() + 1e-12)).max().item())
        # (policy loss and explained variance are differences of nearly equal sums: compare on a 0.01 floor)
        worst["metrics"] = max(worst["metrics"], ((m - ref_m).abs() / (ref_m.abs() + 1e-2)).max().item())
        # continue both from the reference (round-off would otherwise grow through the chaotic dynamics)
        flat.copy_(ref_flat)
        sq.copy_(ref_sq)
        for k in state:
            state[k].copy_(ref_state[k])
        if d.any():
            env.refill(d.any(0))
    assert ends >= hp.num_envs  # episodes ended (auto-reset was exercised)
    assert worst["state"] < 1e-6 and worst["reward"] < 1e-5, worst
    assert worst["flat"] < 1e-5 and worst["sq"] < 1e-3 and worst["metrics"] < 1e-3, worst


def test_training_backends_agree_early_and_native_is_deterministic(tmp_path):
    """Whole runs: the first update's metrics agree across backends; the native run repeats exactly."""
    base = {"a2c": {"compile": False, "log_every": 1, "learning_rate": 1e-3}, "point_mass": {"episode_steps": 30}}
    runs = {}
    for b in ("torch", "native", "native"):
        cfg = config_from_dict({**base, "a2c": {**base["a2c"], "backend": b}})
        res = train(cfg, tmp_path / f"{b}{len(runs)}", total_steps=16 * 40)
        runs[f"{b}{len(runs)}"] = (res, (tmp_path / f"{b}{len(runs)}" / "metrics.csv").read_text().splitlines())
    first = {k: [float(x) for x in v[1][1].split(",")[2:7]] for k, v in runs.items()}
    assert first["torch0"] == pytest.approx(first["native1"], rel=1e-4, abs=1e-5)
    steps_s = runs["native1"][1][0].split(",").index("steps_per_second")  # the one column that differs
    strip = lambda rows: [r.split(",")[:steps_s] + r.split(",")[steps_s + 1:] for r in rows]  # noqa: E731
    assert strip(runs["native1"][1]) == strip(runs["native2"][1])
    assert runs["native1"][0].episode_returns == runs["native2"][0].episode_returns


def test_backend_choice_and_errors(monkeypatch):
    cfg = config_from_dict({"a2c": {"compile": False}})
    env = PointMassEnv(4, cfg, seed=0)
    env.reset()
    layout = ParamLayout(3, 4, cfg.a2c.hidden, cfg.a2c.network)
    gen = torch.Generator()
    assert FusedRollout(env, layout, gen, cfg.a2c)._native is not None  # auto, 16 samples per update
    big = config_from_dict({"a2c": {"compile": False, "num_envs": 128, "n_steps": 16}}).a2c
    big_env = PointMassEnv(128, cfg, seed=0)
    big_env.reset()
    assert FusedRollout(big_env, layout, gen, big)._native is None  # 2048 > AUTO_MAX_BATCH: torch
    forced = config_from_dict({"a2c": {"compile": False, "num_envs": 128, "n_steps": 16, "backend": "native"}}).a2c
    assert FusedRollout(big_env, layout, gen, forced)._native is not None

    class Other(PointMassEnv):  # different dynamics: the C file would simulate the wrong system
        pass

    other = Other(4, cfg, seed=0)
    other.reset()
    assert "PointMassEnv only" in native.unsupported(other, layout)
    assert FusedRollout(other, layout, gen, cfg.a2c)._native is None
    with pytest.raises(ValueError, match="PointMassEnv only"):
        FusedRollout(other, layout, gen, config_from_dict({"a2c": {"backend": "native"}}).a2c)

    monkeypatch.setenv("A3CQP_NATIVE_A2C", "0")
    native._library.reset()
    try:
        assert FusedRollout(env, layout, gen, cfg.a2c)._native is None  # auto falls back to torch
        with pytest.raises(ValueError, match="A3CQP_NATIVE_A2C"):
            FusedRollout(env, layout, gen, config_from_dict({"a2c": {"backend": "native"}}).a2c)
    finally:
        monkeypatch.delenv("A3CQP_NATIVE_A2C")
        native._library.reset()


def test_wrong_inputs_are_refused():
    cfg, hp, env, *_, layout = _setup({})
    it = native.NativeIteration(native.load(), env, layout, hp)
    flat = layout.init()
    state, pending, schedule = env.fused_inputs()
    noise = torch.zeros(hp.n_steps, hp.num_envs, 4)
    with pytest.raises(ValueError, match="noise"):
        it(flat, torch.zeros_like(flat), state, pending, schedule, noise[:, :2])
    with pytest.raises(ValueError, match="square_avg"):
        it(flat, torch.zeros(3), state, pending, schedule, noise)
    with pytest.raises(ValueError, match="x_dot"):
        it(flat, torch.zeros_like(flat), {**state, "x_dot": state["x_dot"].float()}, pending, schedule, noise)
