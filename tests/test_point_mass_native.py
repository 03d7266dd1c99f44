"""envs/native/point_mass.h (the C point mass) against the torch env's agent_step, batched, every scenario."""

import numpy as np
import pytest
import torch

from a3cqp_rl.config import config_from_dict
from envs import native
from envs.point_mass import PointMassEnv, agent_step, observe_state

pytestmark = pytest.mark.skipif(native.load() is None, reason="no C compiler")


@pytest.mark.parametrize("overrides", [{}, {"point_mass": {"operator_model": "drag", "operator_v_hand": 0.2}},
                                       {"point_mass": {"wall_damping": 0.0, "operator_v_hand": 0.05, "substeps": 3,
                                                       "operator_grip": True},
                                            "reward": {"alpha": [1.0, 5.0, 4.0, 2.0]}}])
def test_c_step_equals_torch_step_for_a_whole_episode(overrides):
    cfg = config_from_dict({**overrides, "point_mass": {
        **overrides.get("point_mass", {}), "episode_steps": 300,
        "scenario_probs": {"free": 0.25, "operator": 0.25, "wall": 0.25, "wall_operator": 0.25}}})
    N = 64
    env = PointMassEnv(N, cfg, seed=11)
    env.reset()
    state, schedule = env.functional()
    state = {k: v.clone() for k, v in state.items()}
    c = native.NativePointMass(cfg, N)
    for i in range(N):
        c.set_episode(i, float(state["target"][i]), float(state["wall_pos"][i]), bool(state["has_wall"][i]),
                      int(state["scenario"][i]), state["w_logits"][i].numpy(), float(state["f_d"][i]),
                      schedule[int(state["slot"][i]), i].numpy())
    live = schedule[state["slot"], torch.arange(N)].unsqueeze(0).expand(2, N, -1).contiguous()
    gen = torch.Generator().manual_seed(0)
    worst = {"state": 0.0, "reward": 0.0, "obs": 0.0}
    contact = push = brake = 0
    for _ in range(cfg.point_mass.episode_steps):
        a = (torch.rand(N, 4, generator=gen) * 2.4 - 1.2).float()  # beyond [-1, 1]: both clip
        state, r = agent_step(state, a.double(), live, cfg.point_mass, cfg.adaptation, cfg.reward)
        rc, oc = c.step(np.ascontiguousarray(a.numpy()))
        for k in ("x", "x_dot", "f_env", "f_ope", "f_d", "w_logits"):
            worst["state"] = max(worst["state"], float(np.abs(c.state[k] - state[k].numpy()).max()))
        assert np.array_equal(c.state["t"], state["t"].numpy())
        worst["reward"] = max(worst["reward"], float(np.abs(rc - r.numpy()).max()))
        worst["obs"] = max(worst["obs"], float(np.abs(oc - observe_state(state, cfg.adaptation, torch.float32).numpy()).max()))
        contact += int((state["f_env"] < -1.0).sum())
        push += int((state["f_ope"].abs() > 1.0).sum())
        brake += int((state["f_ope"] * live[0, torch.arange(N), (state["t"] - 1).clamp(min=0)] < -0.1).sum())
    assert worst["state"] < 1e-9 and worst["reward"] < 1e-9 and worst["obs"] < 1e-6, worst
    assert contact > 0 and push > 0  # walls and operators were exercised
    # and the gripping or dragging hand braked a mass running ahead of it
    assert (brake > 0) == (cfg.point_mass.operator_grip or cfg.point_mass.operator_model == "drag")


def test_params_layout_and_bad_library_switch(monkeypatch):
    import ctypes

    assert native.load().pm_params_size() == ctypes.sizeof(native.PMParams)
    monkeypatch.setattr(native, "load", lambda: None)
    with pytest.raises(RuntimeError, match="native point mass is unavailable"):
        native.NativePointMass(config_from_dict({}))


def test_a_config_field_newer_than_the_c_point_mass_trains_on_the_torch_step(monkeypatch, tmp_path):
    import envs.native as pm_native
    from a3cqp_rl.config import ExperimentConfig, config_from_dict
    from algorithms.a2c import train

    assert pm_native.unsupported(ExperimentConfig()) is None  # every field of today's sections is the C file's
    monkeypatch.setitem(pm_native.C_FIELDS, "reward", frozenset())  # as if reward.alpha had been added after it
    assert "not written for reward.alpha" in pm_native.unsupported(ExperimentConfig())
    res = train(config_from_dict({"a2c": {"compile": False}}), tmp_path / "r", total_steps=16 * 4, progress=False)
    assert res.route.startswith("the torch step") and "reward.alpha" in res.route
    monkeypatch.undo()
    res = train(config_from_dict({"a2c": {"compile": False}}), tmp_path / "c", total_steps=16 * 4, progress=False)
    assert res.route.startswith("the C iteration")
