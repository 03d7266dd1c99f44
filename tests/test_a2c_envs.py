"""A2C on envs other than the point mass: sizes and bounds from the specs, gymnasium ids, agent dims, TorchRL actors."""

import csv
import math

import pytest
import torch
from tensordict import TensorDict
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

from a3cqp_rl.config import config_from_dict
from algorithms.a2c import EnvLayout, load_actor, load_policy, read_env_layout, train
from algorithms.policy import first_episode_returns

FAST = {"compile": False, "log_every": 4, "region_checks": 5}


def _rows(run):
    with (run / "metrics.csv").open() as f:
        return list(csv.DictReader(f))


def test_pendulum_reads_its_specs_scales_actions_and_skips_the_fig5_checks(tmp_path):
    cfg = config_from_dict({"env": "Pendulum-v1", "a2c": {**FAST, "num_envs": 3}})
    res = train(cfg, tmp_path / "run", total_steps=3 * 4 * 8)
    saved = torch.load(res.policy_path, weights_only=True)
    assert saved["layout"][:2] == [3, 1] and saved["action_low"] == [-2.0] and saved["action_high"] == [2.0]
    assert saved["env"] == "Pendulum-v1"
    assert all(r["regions_ok"] == "nan" for r in _rows(tmp_path / "run")) and not res.fig5_applies
    policy = load_policy(res.policy_path)
    a = policy(torch.randn(7, 3))
    assert a.shape == (7, 1) and a.abs().max() <= 2.0


def test_a_resume_of_a_gymnasium_run_says_its_episodes_start_again(tmp_path, caplog):
    """A collector-driven env is not snapshotted: the resume continues parameters and optimiser, and says so."""
    cfg = config_from_dict({"env": "Pendulum-v1", "a2c": {**FAST, "num_envs": 2}})
    train(cfg, tmp_path / "run", total_steps=2 * 4 * 4)
    with caplog.at_level("WARNING", logger="algorithms.a2c"):
        res = train(cfg, tmp_path / "run", total_steps=2 * 4 * 8, resume=True)
    assert res.steps == 64 and "episodes start again from the seed" in caplog.text


def test_mountain_car_with_two_observations_trains():
    # 2 observations, 1 action in [-1, 1]: was "shape '[-1, 3]' is invalid" with the point mass's sizes hard-coded
    cfg = config_from_dict({"env": "MountainCarContinuous-v0", "a2c": {**FAST, "num_envs": 2}})
    res = train(cfg, None, total_steps=2 * 4 * 6)
    assert res.updates == 6 and math.isfinite(res.final_metrics["value_loss"])


def test_actions_map_onto_the_spec_bounds():
    spec = EnvLayout(3, 2, 4, (), (-2.0, 0.0), (2.0, 10.0))
    raw = torch.tensor([[-1.0, -1.0], [1.0, 1.0], [0.0, 0.5], [-7.0, 3.0]])
    assert torch.equal(spec.to_env(raw), torch.tensor([[-2.0, 0.0], [2.0, 10.0], [0.0, 7.5], [-2.0, 10.0]]))
    unit = EnvLayout(3, 4, 4, (), (-1.0,) * 4, (1.0,) * 4)
    x = torch.randn(100, 4)
    assert unit.unit_bounds() and torch.equal(unit.to_env(x), x.clamp(-1, 1))  # bit-identical on the point mass
    assert torch.equal(EnvLayout(3, 1, 1).to_env(x), x)  # unbounded: as sampled


def test_env_layout_of_the_point_mass_and_of_unsupported_specs():
    from envs.point_mass import PointMassEnv

    spec = read_env_layout(PointMassEnv(5))
    assert (spec.obs_dim, spec.act_dim, spec.num_envs, spec.agents, spec.low, spec.high) == (3, 4, 5, (), (-1.0,) * 4, (1.0,) * 4)
    env = _AgentsEnv(2)
    env.action_spec = Categorical(3, shape=(2, 2, 1))
    with pytest.raises(ValueError, match="continuous"):
        read_env_layout(env)


def test_a_passed_env_is_seeded_and_must_match_num_envs(tmp_path):
    from algorithms.make_env import gym_env

    cfg = config_from_dict({"env": "Pendulum-v1", "seed": 3, "a2c": {**FAST, "num_envs": 2}})
    with pytest.raises(ValueError, match="a2c.num_envs is 2 but the env passed has 4"):
        train(cfg, None, total_steps=64, env=gym_env("Pendulum-v1", 4, seed=0))
    # envs built with other seeds, then seeded by train with cfg.seed: the same run
    flats = []
    for env_seed in (0, 99):
        res = train(cfg, tmp_path / str(env_seed), total_steps=2 * 4 * 30, env=gym_env("Pendulum-v1", 2, seed=env_seed))
        flats.append(torch.load(res.policy_path, weights_only=True)["flat"])
    assert torch.equal(*flats)


class _AgentsEnv(EnvBase):
    """N envs × 2 agents sharing a policy: obs [N, 2, 3], action [N, 2, 1] in [0, 4], one reward per env;
    reward = −Σ_agents (action − 4·obs[0])², episodes of 5 steps."""

    def __init__(self, n: int) -> None:
        super().__init__(batch_size=torch.Size([n]))
        self.observation_spec = Composite(observation=Unbounded(shape=(n, 2, 3)), shape=(n,))
        self.action_spec = Bounded(0.0, 4.0, shape=(n, 2, 1))
        self.reward_spec = Unbounded(shape=(n, 1))
        flag = Categorical(2, shape=(n, 1), dtype=torch.bool)
        self.done_spec = Composite(done=flag.clone(), terminated=flag.clone(), truncated=flag.clone(), shape=(n,))
        self.rng = torch.Generator()
        self.t = torch.zeros(n, dtype=torch.int64)

    def _set_seed(self, seed):
        self.rng.manual_seed(int(seed))

    def _obs(self, n):
        return torch.rand(n, 2, 3, generator=self.rng)

    def _reset(self, td=None, **kw):
        n = self.batch_size[0]
        self.t.zero_()
        self.obs = self._obs(n)
        z = torch.zeros(n, 1, dtype=torch.bool)
        return TensorDict(observation=self.obs.clone(), done=z, terminated=z.clone(), truncated=z.clone(), batch_size=[n])

    def _step(self, td):
        n = self.batch_size[0]
        r = -((td["action"][..., 0] - 4 * self.obs[..., 0]) ** 2).sum(-1, keepdim=True)
        self.t += 1
        trunc = (self.t >= 5).unsqueeze(-1)
        self.obs = self._obs(n)
        return TensorDict(observation=self.obs.clone(), reward=r, done=trunc.clone(), terminated=torch.zeros_like(trunc),
                          truncated=trunc, batch_size=[n])


def test_agent_dims_share_one_policy_and_it_learns_the_bounded_target(tmp_path):
    env = _AgentsEnv(4)
    assert read_env_layout(env).agents == (2,)
    cfg = config_from_dict({"env": "Pendulum-v1", "a2c": {**FAST, "num_envs": 4, "n_steps": 5, "learning_rate": 3e-3,
                                                          "gamma": 0.01, "log_every": 50, "normalize_advantage": True}})
    res = train(cfg, tmp_path / "run", total_steps=4 * 5 * 400, env=env)
    saved = torch.load(res.policy_path, weights_only=True)
    assert saved["agents"] == [2] and saved["layout"][:2] == [3, 1] and saved["action_high"] == [4.0]
    policy = load_policy(res.policy_path)
    obs = torch.rand(200, 3)
    err = (policy(obs)[:, 0] - 4 * obs[:, 0]).abs().mean()
    assert err < 0.6, err  # a random policy (mean 2, clipped) misses by ~1.0 on average
    assert res.episode_returns and len(res.episode_returns) % 2 == 0  # both agents of an env count each episode


def test_load_actor_is_a_torchrl_policy_for_env_rollout(tmp_path):
    from tensordict.nn import InteractionType
    from torchrl.envs.utils import ExplorationType, set_exploration_type

    from algorithms.make_env import gym_env

    cfg = config_from_dict({"env": "Pendulum-v1", "a2c": {**FAST, "num_envs": 2, "log_std_init": 0.0}})
    train(cfg, tmp_path / "run", total_steps=64)
    actor = load_actor(tmp_path / "run" / "policy.pt").to("cpu")
    assert sum(p.numel() for p in actor.parameters()) > 0
    env = gym_env("Pendulum-v1", 2, seed=0)
    td = env.rollout(6, policy=actor)
    assert td["action"].shape == (2, 6, 1)
    mean = load_policy(tmp_path / "run" / "policy.pt")
    assert torch.allclose(td["action"], mean(td["observation"]))  # the mean by default
    sampler = load_actor(tmp_path / "run" / "policy.pt", sample=True)
    assert sampler.default_interaction_type == InteractionType.RANDOM
    with set_exploration_type(ExplorationType.RANDOM):
        draws = torch.stack([actor(td[:, 0].clone())["action"] for _ in range(20)])
    assert draws.std(0).min() > 0.1 and draws.abs().max() <= 2.0  # sampled (std 2·e^0), projected onto the bounds


def test_cli_trains_a_gymnasium_task_by_name(tmp_path, capsys):
    from a3cqp_rl.cli import main

    out = tmp_path / "pend"
    assert main(["train", "--env", "Pendulum-v1", "--steps", "128", "--no-compile", "--quiet", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "Fig. 5" not in printed and (out / "loss_curves.png").is_file() and not (out / "policy_map.png").exists()
    assert torch.load(out / "policy.pt", weights_only=True)["env"] == "Pendulum-v1"
    assert main(["train", "--env", "NoSuchEnv-v9", "--steps", "128", "--out", str(tmp_path / "x")]) == 2
    assert "NoSuchEnv-v9" in capsys.readouterr().err


def test_linear_learning_rate_schedule_on_the_torchrl_rollout():
    import pytest

    cfg = config_from_dict({"env": "Pendulum-v1", "a2c": {**FAST, "num_envs": 2, "lr_schedule": "linear",
                                                          "learning_rate": 1e-2}})
    seen = []
    from algorithms import a2c

    original = a2c.TorchRLRollout.iterate

    def spy(self, flat, sq):
        seen.append(float(self.lr))
        return original(self, flat, sq)

    a2c.TorchRLRollout.iterate = spy
    try:
        train(cfg, None, total_steps=2 * 4 * 4)
    finally:
        a2c.TorchRLRollout.iterate = original
    assert seen == pytest.approx([1e-2, 0.75e-2, 0.5e-2, 0.25e-2])
    with pytest.raises(ValueError, match="lr_schedule"):  # the fused point-mass iteration keeps λη constant
        train(config_from_dict({"a2c": {**FAST, "lr_schedule": "linear"}}), None, total_steps=32)


def test_reward_scale_scales_what_the_update_learns_from_not_the_logged_returns():
    from algorithms import a2c

    rewards, original = [], a2c.a2c_update

    def spy(layout, flat, sq, batch, hp, lr=None):
        rewards.append(batch.rewards.clone())
        return original(layout, flat, sq, batch, hp, lr)

    a2c.a2c_update = spy
    try:
        runs = [train(config_from_dict({"env": "Pendulum-v1", "a2c": {**FAST, "num_envs": 2, "reward_scale": s}}), None,
                      total_steps=2 * 4) for s in (1.0, 0.25)]
    finally:
        a2c.a2c_update = original
    assert torch.allclose(rewards[1], 0.25 * rewards[0]) and bool((rewards[0] < -0.01).any())
    assert runs[0].final_metrics["step"] == runs[1].final_metrics["step"] == 8


def test_first_episode_returns_sums_each_envs_first_episode(tmp_path):
    cfg = config_from_dict({"env": "Pendulum-v1", "a2c": {**FAST, "num_envs": 2}})
    res = train(cfg, tmp_path / "run", total_steps=64)
    from algorithms.make_env import gym_env

    env = gym_env("Pendulum-v1", 3, seed=5)
    returns = first_episode_returns(res.policy_path, env, 250)  # Pendulum: 200 steps, then auto-reset
    env2 = gym_env("Pendulum-v1", 3, seed=5)
    td = env2.rollout(200, policy=load_actor(res.policy_path))
    assert torch.allclose(returns, td["next", "reward"].sum((1, 2)))
    with pytest.raises(ValueError, match="max_steps"):
        first_episode_returns(res.policy_path, gym_env("Pendulum-v1", 3, seed=5), 150)
