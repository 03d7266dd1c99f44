"""PointMassEnv: TorchRL specs, batching, determinism, eq. 35 behaviour per scenario, bad input."""

import pytest
import torch
from tensordict import TensorDict
from torchrl.envs.utils import check_env_specs

from a3cqp_rl.config import ExperimentConfig, config_from_dict
from envs.point_mass import PRIVILEGED_DIM, SCENARIOS, PointMassEnv


def scenario_env(n, scenario, seed=0, **pm):
    cfg = config_from_dict({"point_mass": {"scenario_probs": {scenario: 1.0}, "random_initial_weights": False, **pm}})
    return PointMassEnv(n, cfg, seed=seed)


def run_const(env, action, steps):
    """Roll out a constant action [4] for all envs; returns the stacked TensorDict [N, steps]."""
    a = torch.tensor(action, dtype=torch.float32).expand(env.num_envs, 4)
    td = env.reset()
    out = []
    for _ in range(steps):
        td = env.step(td.set("action", a.clone()))
        out.append(td["next"].clone())
        td = td["next"]
    return torch.stack(out, dim=1)


@pytest.mark.parametrize("n", [1, 4, 4096])
def test_specs_and_batch_sizes(n):
    env = PointMassEnv(n, seed=1)
    check_env_specs(env)
    td = env.rollout(3, break_when_any_done=False)
    assert td.batch_size == (n, 3)
    assert td["next", "observation"].shape == (n, 3, 3)
    assert td["next", "reward"].shape == (n, 3, 1)
    assert td["next", "w"].shape == (n, 3, 3)
    obs = td["next", "observation"]
    assert obs.min() >= 0 and obs.max() <= 1


def test_same_seed_same_trajectory_and_other_seed_differs():
    def traj(seed):
        env = PointMassEnv(8, seed=seed)
        torch.manual_seed(123)  # random actions drawn from the global RNG, same for both runs
        return env.rollout(200, break_when_any_done=False)

    a, b, c = traj(5), traj(5), traj(6)
    assert torch.equal(a["next", "x"], b["next", "x"]) and torch.equal(a["next", "reward"], b["next", "reward"])
    assert not torch.equal(a["next", "x"], c["next", "x"])


def test_ik_tracks_target_in_free_motion():
    env = scenario_env(16, "free")
    td = run_const(env, [1.0, -1.0, -1.0, -1.0], 300)  # w1 -> 1, f_d -> 0
    e_final = td["e"][:, -1].abs()
    assert e_final.max() < 1e-3, e_final.max()
    assert td["f_d"][:, -1].max() == 0.0


def test_admittance_yields_to_operator():
    ik = run_const(scenario_env(32, "operator", seed=3), [1.0, -1.0, -1.0, -1.0], 400)
    ac = run_const(scenario_env(32, "operator", seed=3), [-1.0, 1.0, -1.0, -1.0], 400)
    f_ik, f_ac = ik["f_ope"].abs().mean(), ac["f_ope"].abs().mean()
    assert f_ik > 1.0  # the operator really pushes in this scenario
    assert f_ac < 0.5 * f_ik, (f_ac, f_ik)
    # and the reward (eq. 30) says so
    assert ac["reward"].mean() > ik["reward"].mean()


def test_force_control_presses_wall_with_desired_force():
    env = scenario_env(8, "wall")
    td = run_const(env, [-1.0, -1.0, 1.0, 1.0], 400)  # w3 -> ~1, f_d -> f̄_d = 20 N
    f_env = td["f_env"][:, -50:]
    assert torch.allclose(td["f_d"][:, -1], torch.full((8,), 20.0, dtype=torch.float64))
    w3 = td["w"][:, -1, 2]
    # steady contact force balances w3 f_d plus the (small) residual IK pull towards the target
    assert ((-f_env.mean(-1)) / (w3 * 20.0) - 1).abs().max() < 0.05
    assert f_env.std(-1).max() < 0.2  # settled, no chatter
    # the wall is a spring: penetration = contact force / stiffness (5000 N/m)
    pen = td["x"][:, -1] - env.functional()[0]["wall_pos"]
    assert torch.allclose(pen, -f_env[:, -1] / 5000.0, rtol=0.02)


def test_scenarios_sampled_with_configured_probabilities():
    env = PointMassEnv(4096, config_from_dict({"point_mass": {"scenario_probs": {"free": 0.5, "wall": 0.5}}}), seed=0)
    td = env.reset()
    counts = torch.bincount(td["scenario"], minlength=len(SCENARIOS)).double() / 4096
    assert abs(counts[0] - 0.5) < 0.05 and abs(counts[2] - 0.5) < 0.05 and counts[1] == 0 and counts[3] == 0


def test_operator_schedule_starts_and_stops():
    env = scenario_env(64, "operator", operator_force_min=5.0)
    env.reset()
    state, sched = env.functional()
    sched = sched[state["slot"], torch.arange(64)]  # the live slot of each env: [N, T+1]
    on = sched.abs() > 0
    assert on.any(-1).all() and (~on).any(-1).all()  # every env has push and pause phases
    assert sched.abs().max() <= 15.0 and sched[on].abs().min() >= 5.0


@pytest.mark.parametrize("toward", [0.5, 0.2, 1.0])
def test_operator_toward_wall_sets_the_share_of_pushes_to_the_wall_side(toward):
    env = scenario_env(256, "operator", operator_toward_wall=toward)
    env.reset()
    state, sched = env.functional()
    sched = sched[state["slot"], torch.arange(256)]
    pushes = sched[sched != 0]
    share = (pushes > 0).double().mean().item()  # of the agent steps pushed (a phase's length does not depend on it)
    assert abs(share - toward) < 0.05, share


def test_operator_toward_wall_is_a_probability():
    with pytest.raises(Exception, match="operator_toward_wall"):
        config_from_dict({"point_mass": {"operator_toward_wall": 1.5}})


def test_truncation_at_episode_end_and_partial_reset():
    env = PointMassEnv(3, config_from_dict({"point_mass": {"episode_steps": 5}}), seed=0)
    td = env.rollout(5, break_when_any_done=False)
    assert td["next", "truncated"][:, -1].all() and not td["next", "terminated"].any()
    assert not td["next", "done"][:, :-1].any()
    before = env.functional()[0]["target"].clone()
    env.reset(TensorDict({"_reset": torch.tensor([[True], [False], [False]])}, batch_size=[3]))
    after = env.functional()[0]
    assert after["t"].tolist() == [0, 5, 5]
    assert torch.equal(after["target"][1:], before[1:])


def test_bad_actions_raise_clear_errors():
    env = PointMassEnv(4, seed=0)
    td = env.reset()
    with pytest.raises(ValueError, match="NaN"):
        env.step(td.clone().set("action", torch.full((4, 4), float("nan"))))
    with pytest.raises((ValueError, RuntimeError)):
        env.step(td.clone().set("action", torch.zeros(4, 3)))
    with pytest.raises(ValueError, match="num_envs"):
        PointMassEnv(0)
    # an action with a graph (a policy run without no_grad) is detached: the state must not grow a graph step by step
    net = torch.nn.Linear(3, 4)
    out = env.step(td.clone().set("action", torch.tanh(net(td["observation"]))))["next"]
    assert not out["observation"].requires_grad and not out["reward"].requires_grad
    assert not any(torch.is_tensor(v) and v.requires_grad for v in env._state.values())


def test_fused_step_with_auto_reset_equals_torchrl_step_then_reset():
    """The fused path (pending episode, auto-reset) yields the same trajectory as step + TorchRL reset."""
    cfg = config_from_dict({"point_mass": {"episode_steps": 7}})
    a, b = PointMassEnv(5, cfg, seed=11), PointMassEnv(5, cfg, seed=11)
    a.reset()
    g = torch.Generator().manual_seed(0)
    td = b.reset()
    step_fn, _ = a.fused_functions()
    for step in range(20):
        act = 2 * torch.rand(5, 4, generator=g) - 1
        state, pending, sched = a.fused_inputs()
        new_state, final_obs, next_obs, r, term, trunc = step_fn(state, pending, sched, act)
        a.fused_commit(new_state)
        # b: TorchRL step; at the episode end, reset b to the very episode a switched to
        out = b.step(td.set("action", act.clone()))["next"]
        assert torch.allclose(out["observation"], final_obs) and torch.allclose(out["reward"].squeeze(-1), r)
        assert torch.equal(out["truncated"].squeeze(-1), trunc)
        if trunc.any():
            b.set_state(a.get_state())
            a.refill(trunc)
            td = b._observation_td(torch.zeros(5, 1, dtype=torch.bool))
            assert torch.equal(a.functional()[0]["t"], torch.zeros(5, dtype=torch.int64))
        else:
            td = out
        assert torch.allclose(td["observation"], next_obs)


def test_privileged_critic_observation_extends_the_eq26_observation():
    env = PointMassEnv(6, seed=3)
    td = env.rollout(40, break_when_any_done=False)
    crit = td["next", "critic_observation"]
    assert crit.shape == (6, 40, 3 + PRIVILEGED_DIM)
    assert torch.equal(crit[..., :3], td["next", "observation"])
    # the hidden integrator states ride along: softmax weights then f_d / f̄_d
    assert torch.allclose(crit[..., 3:6], td["next", "w"].float(), atol=1e-6)
    assert torch.allclose(crit[..., 6], (td["next", "f_d"] / env.adapt.f_d_max).float(), atol=1e-6)
    assert crit.abs().max() <= 1.0 + 1e-6
    # the fused path gives the same vector
    env.reset()
    step_fn, obs_fn = env.fused_functions(privileged=True)
    state, pending, sched = env.fused_inputs()
    assert obs_fn(state).shape == (6, 3 + PRIVILEGED_DIM)
    out = step_fn(state, pending, sched, torch.zeros(6, 4))
    assert out[1].shape == out[2].shape == (6, 3 + PRIVILEGED_DIM)


def test_an_unmeasured_disturbance_leaves_the_ik_error_it_predicts_and_drifts_without_ik():
    env = scenario_env(8, "free", disturbance_max=10.0, target_min=0.0, target_max=1e-6, episode_steps=400)
    td = run_const(env, [1.0, -1.0, -1.0, -1.0], 300)  # IK: 3 s, settled
    d = env._state["disturbance"]
    assert d.abs().max() <= 10.0 and d.abs().min() > 0 and len(set(d.tolist())) == 8
    w1 = td["w"][:, -1, 0]
    # steady state of eq. 35 with the extra force: w1 Λ Kp e = −d (the sensors read nothing)
    expected = -d / (w1 * env.cfg.mass * env.cfg.kp)
    assert torch.allclose(td["e"][:, -1], expected, rtol=1e-3)
    assert td["f_env"].abs().max() == 0 and td["f_ope"].abs().max() == 0
    # with IK's weight driven down the mass drifts far along the force
    td = run_const(env, [-1.0, 1.0, 1.0, -1.0], 300)  # (new episodes, new forces)
    ik_error = env._state["disturbance"] / (env.cfg.mass * env.cfg.kp)  # what full IK would leave
    assert (td["e"][:, -1].abs() > 100 * ik_error.abs()).all()
    # only free episodes carry one; validation and the C point mass refuse it
    e2 = PointMassEnv(64, config_from_dict({"point_mass": {"scenario_probs": {"free": 0.5, "wall": 0.5},
                                                             "disturbance_max": 5.0}}), seed=1)
    e2.reset()
    s = e2._state
    assert torch.all(s["disturbance"][s["scenario"] != 0] == 0) and torch.any(s["disturbance"] != 0)
    with pytest.raises(Exception, match="disturbance_max"):
        config_from_dict({"point_mass": {"disturbance_max": float("nan")}})
    from envs.native import unsupported
    assert "disturbance" in unsupported(config_from_dict({"point_mass": {"disturbance_max": 1.0}}))


def test_a_moving_target_is_tracked_and_keeps_its_speed_through_resets():
    env = scenario_env(8, "free", target_speed_max=0.1, target_min=0.0, target_max=1e-3, episode_steps=200)
    td = run_const(env, [1.0, -1.0, -1.0, -1.0], 150)  # IK: 1.5 s of tracking, one episode
    speed = env._state["target_speed"]
    assert speed.abs().max() <= 0.1 and speed.abs().min() > 0 and len(set(speed.tolist())) == 8
    moved = td["target"][:, -1] - td["target"][:, 0]
    assert torch.allclose(moved, speed * 1.49, atol=1e-9)
    assert td["e"][:, -1].abs().max() < 1e-4  # with ė = ẋ_d − ẋ there is no lag
    # the pending episode carries its own speed; only free episodes move
    env2 = config_from_dict({"point_mass": {"scenario_probs": {"free": 0.5, "wall": 0.5}, "target_speed_max": 0.1}})
    e2 = PointMassEnv(64, env2, seed=1)
    e2.reset()
    s = e2._state
    assert torch.all(s["target_speed"][s["scenario"] != 0] == 0) and torch.any(s["target_speed"] != 0)
    assert "target_speed" in e2._pending and not torch.equal(e2._pending["target_speed"], s["target_speed"])


def test_idle_force_damps_the_share_of_force_control_that_does_not_push():
    def coast(idle_force: str) -> float:
        env = scenario_env(1, "free", idle_force=idle_force, target_min=0.3, target_max=0.3)
        env.reset()
        env._state["x_dot"][:] = 0.1
        env._state["w_logits"][:] = torch.tensor([-3.0, -3.0, 3.0], dtype=torch.float64)  # w3 ≈ 1, f_d = 0
        td = env.reset(TensorDict({"_reset": torch.zeros(1, 1, dtype=torch.bool)}, batch_size=[1]))
        td = env.step(td.set("action", torch.tensor([[0.0, 0.0, 0.0, -1.0]])))
        return float(env._state["x_dot"][0])

    free, damps = coast("free"), coast("damps")
    assert free > 0.099  # eq. 35: an idle force-control share commands nothing, the mass coasts
    # damps: the share damps as IK does, Kv ≈ 24.5 1/s for 10 ms
    assert damps < 0.085, damps
    with pytest.raises(Exception, match="idle_force"):
        config_from_dict({"point_mass": {"idle_force": "holds"}})
    with pytest.raises(Exception, match="target_speed_max"):
        config_from_dict({"point_mass": {"target_speed_max": -0.1}})


def test_the_c_point_mass_refuses_what_it_does_not_simulate():
    from envs.native import unsupported

    assert unsupported(ExperimentConfig()) is None
    assert "fixed targets" in unsupported(config_from_dict({"point_mass": {"target_speed_max": 0.05}}))
    assert "idle_force" in unsupported(config_from_dict({"point_mass": {"idle_force": "damps"}}))
    assert "operator_toward_wall" in unsupported(config_from_dict({"point_mass": {"operator_toward_wall": 0.25}}))
