"""envs.gym_vector.GymVectorEnv: gymnasium's vector env as a TorchRL env, step for step what gymnasium does."""

import gymnasium as gym
import numpy as np
import pytest
import torch
from torchrl.envs import GymWrapper
from torchrl.envs.utils import check_env_specs

from algorithms.make_env import gym_env
from envs.gym_vector import GymVectorEnv, supported


class Countdown(gym.Env):
    """A 1-D task whose episodes end after a random 2-6 steps, terminated or truncated at random: envs of a vector
    end at different steps, and some at the same one."""

    observation_space = gym.spaces.Box(-10.0, 10.0, (3,), np.float32)
    action_space = gym.spaces.Box(-1.0, 1.0, (2,), np.float32)

    def reset(self, *, seed=None, options=None):
        super().reset(seed=seed)
        self.left = int(self.np_random.integers(2, 7))
        self.x = self.np_random.normal(size=3).astype(np.float32)
        return self.x.copy(), {}

    def step(self, action):
        self.x = (self.x + action.sum()).astype(np.float32)
        self.left -= 1
        end = self.left == 0
        cut = end and bool(self.np_random.integers(2))
        return self.x.copy(), float(self.x.sum()), end and not cut, cut, {}


def _vec(n: int, env=Countdown):
    return gym.vector.SyncVectorEnv([env] * n, autoreset_mode=gym.vector.AutoresetMode.SAME_STEP)


def test_specs_check_and_a_pendulum_rollout_matches_torchrls_gymwrapper():
    check_env_specs(gym_env("Pendulum-v1", 3, seed=4))
    env = gym_env("Pendulum-v1", 3, seed=4)
    assert isinstance(env, GymVectorEnv)
    ref = gym_env("Pendulum-v1", 3, seed=4, torchrl_wrapper=True)
    assert isinstance(ref.base_env, GymWrapper)
    actions = torch.rand(150, 3, 1, generator=torch.Generator().manual_seed(0)) * 4 - 2
    a, b = env.reset(), ref.reset()
    for act in actions:  # within the first episode (Pendulum truncates at 200 steps)
        a, b = env.step(a.set("action", act))["next"], ref.step(b.set("action", act))["next"]
        for key in ("observation", "reward", "done", "terminated", "truncated"):
            assert torch.equal(a[key], b[key]), key
    assert env.action_spec.dtype == ref.action_spec.dtype and torch.equal(env.action_spec.space.high,
                                                                            ref.action_spec.space.high)


def test_episode_ends_give_the_final_observation_then_gymnasiums_reset_one():
    n, steps = 5, 40
    env, ref = GymVectorEnv(_vec(n)), _vec(n)
    env.set_seed(7)
    ref.reset(seed=7)  # set_seed resets with the seed; the rollout's reset draws the first states
    expected, _ = ref.reset()
    rng = np.random.default_rng(1)
    td = env.reset()
    ends = []
    for _ in range(steps):
        act = rng.uniform(-1, 1, (n, 2)).astype(np.float32)
        assert np.array_equal(td["observation"].numpy(), expected)  # the root: where each env starts the step
        obs, rew, term, trunc, info = ref.step(act)
        out, td = env.step_and_maybe_reset(td.set("action", torch.from_numpy(act)))
        done = term | trunc
        final = obs.copy()
        if done.any():
            final[done] = np.stack(info["final_obs"][done])
        assert np.array_equal(out["next", "observation"].numpy(), final)  # bootstrapping reads the last one
        assert np.array_equal(out["next", "reward"].numpy()[:, 0], rew.astype(np.float32))
        assert np.array_equal(out["next", "terminated"].numpy()[:, 0], term)
        assert np.array_equal(out["next", "truncated"].numpy()[:, 0], trunc)
        assert np.array_equal(out["next", "done"].numpy()[:, 0], done)
        expected = obs
        ends.append(done)
    ends = np.array(ends)
    assert ends.any(1).sum() > 5 and (ends.sum(1) < n).any() and (ends.sum(1) > 1).any()  # partial and joint ends


def test_a_reset_asked_for_envs_still_running_resets_only_those():
    env = GymVectorEnv(_vec(4))
    env.set_seed(0)
    td = env.reset()
    td = env.step(td.set("action", torch.zeros(4, 2)))["next"]  # one step: no episode has ended
    before = td["observation"].clone()
    after = env.reset(td.set("_reset", torch.tensor([[True], [False], [True], [False]])))["observation"]
    assert torch.equal(after[[1, 3]], before[[1, 3]])
    assert not torch.equal(after[[0, 2]], before[[0, 2]])


def test_other_spaces_go_through_torchrls_gymwrapper_and_the_env_refuses_them():
    env = gym_env("CartPole-v1", 2, seed=0)  # a discrete action
    assert isinstance(env.base_env, GymWrapper) and not isinstance(env, GymVectorEnv)
    vec = gym.make_vec("CartPole-v1", num_envs=2, vectorization_mode="sync",
                       vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP})
    assert not supported(vec)
    with pytest.raises(ValueError, match="Box"):
        GymVectorEnv(vec)
    with pytest.raises(ValueError, match="SAME_STEP"):
        GymVectorEnv(gym.vector.SyncVectorEnv([Countdown] * 2))  # gymnasium's default: NEXT_STEP


class _DictObs(gym.Env):
    observation_space = gym.spaces.Dict({"observation": gym.spaces.Box(-1, 1, (3,)), "goal": gym.spaces.Box(-1, 1, (3,))})
    action_space = gym.spaces.Box(-1, 1, (2,))


class _Unbounded(gym.Env):
    observation_space = gym.spaces.Box(-1, 1, (3,))
    action_space = gym.spaces.Box(-np.inf, np.inf, (2,))

    def reset(self, seed=None, options=None):  # noqa: ANN001, ANN201
        super().reset(seed=seed)
        return np.zeros(3, np.float32), {}

    def step(self, action):  # noqa: ANN001, ANN201
        return np.zeros(3, np.float32), float(np.sum(action)), False, False, {}


def test_a_composite_observation_is_named_and_an_unbounded_action_passes_as_sampled():
    """A Dict observation used to train on its 'observation' key alone and crash at the first episode end inside
    TorchRL's wrapper; an unbounded action (±3.4e38 in TorchRL's spec) used to be scaled to inf."""
    from algorithms.a2c import read_env_layout

    gym.register("A3CQPTestDictObs-v0", entry_point=_DictObs, max_episode_steps=5)
    gym.register("A3CQPTestUnbounded-v0", entry_point=_Unbounded, max_episode_steps=5)
    with pytest.raises(ValueError, match=r"observation space is Dict; the A2C reads a Box observation.*FlattenObservation"):
        gym_env("A3CQPTestDictObs-v0", 2, seed=0)
    layout = read_env_layout(gym_env("A3CQPTestUnbounded-v0", 2, seed=0))
    assert layout.low is None and layout.high is None
    assert torch.equal(layout.to_env(torch.tensor([[0.0, 0.5]])), torch.tensor([[0.0, 0.5]]))


def test_a_gymnasium_mujoco_task_runs_with_its_float64_observations_and_uneven_episode_ends():
    env = gym_env("InvertedPendulum-v5", 4, seed=0)  # needs gymnasium[mujoco] (imageio), a project dependency
    assert isinstance(env, GymVectorEnv) and env.observation_spec["observation"].dtype == torch.float64
    check_env_specs(env)
    td = env.rollout(120, break_when_any_done=False)  # random actions: the pole falls within tens of steps
    ends = td["next", "done"][..., 0]
    assert ends.any(1).all() and not torch.equal(ends[0], ends[1])  # every env ended, at different steps
    assert torch.isfinite(td["next", "observation"]).all()
