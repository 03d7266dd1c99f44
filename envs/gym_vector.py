"""Gymnasium's synchronous vector env as a TorchRL EnvBase, batch_size [N], for flat Box observations and actions.

TorchRL's `GymWrapper` handles every gymnasium space, info dict and backend, and costs about five times Pendulum-v1's
own step doing so (its info reader and `VecGymEnvTransform` run on every step). This env reads only what the A2C
needs: the observation, reward, terminated and truncated, and the final observation of an episode that ends
(gymnasium's SAME_STEP auto-reset), so that "next" observation is the episode's last one (for bootstrapping at
truncation) and the collector's partial reset gets the observation gymnasium has already reset to. Other spaces go
through `GymWrapper` (`algorithms.make_env.gym_env`).
"""

from __future__ import annotations

import gymnasium as gym
import numpy as np
import torch
from tensordict import TensorDict, TensorDictBase
from torchrl.data import Bounded, Categorical, Composite, Unbounded
from torchrl.envs import EnvBase

__all__ = ["GymVectorEnv", "supported"]


def supported(env: gym.vector.VectorEnv) -> bool:
    """Whether `env`'s single observation and action spaces are 1-D float Boxes (what GymVectorEnv reads)."""
    spaces = (env.single_observation_space, env.single_action_space)
    return all(isinstance(s, gym.spaces.Box) and len(s.shape) == 1 and np.issubdtype(s.dtype, np.floating)
               for s in spaces)


def _box_spec(space: gym.spaces.Box, n: int) -> Bounded | Unbounded:
    """The TorchRL spec of `n` stacked copies of a 1-D Box (Bounded where every bound is finite)."""
    dtype = torch.from_numpy(np.zeros(0, dtype=space.dtype)).dtype
    shape = (n, *space.shape)
    if np.isfinite(space.low).all() and np.isfinite(space.high).all():
        low = torch.as_tensor(np.broadcast_to(space.low, shape).copy(), dtype=dtype)
        high = torch.as_tensor(np.broadcast_to(space.high, shape).copy(), dtype=dtype)
        return Bounded(low, high, shape=shape, dtype=dtype)
    return Unbounded(shape=shape, dtype=dtype)


class GymVectorEnv(EnvBase):
    """`vec` (a gymnasium vector env in SAME_STEP auto-reset mode, 1-D float Box spaces) as a TorchRL env."""

    def __init__(self, vec: gym.vector.VectorEnv) -> None:
        if not supported(vec):
            raise ValueError("GymVectorEnv reads 1-D float Box observation and action spaces; use TorchRL's GymWrapper")
        if vec.metadata.get("autoreset_mode") != gym.vector.AutoresetMode.SAME_STEP:
            raise ValueError("GymVectorEnv needs gymnasium's SAME_STEP auto-reset (the final observation in the step)")
        n = vec.num_envs
        super().__init__(batch_size=torch.Size([n]))
        self._vec = vec
        self.observation_spec = Composite(observation=_box_spec(vec.single_observation_space, n), shape=(n,))
        self.action_spec = _box_spec(vec.single_action_space, n)
        self.reward_spec = Unbounded(shape=(n, 1), dtype=torch.float32)
        flag = Categorical(2, shape=(n, 1), dtype=torch.bool)
        self.done_spec = Composite(done=flag, terminated=flag.clone(), truncated=flag.clone(), shape=(n,))
        self._obs_dtype = self.observation_spec["observation"].dtype
        self._last_obs: np.ndarray | None = None  # the vector env's observation after the last step (reset ones in)
        self._ended = np.zeros(n, dtype=bool)  # the envs whose episode ended in the last step (already reset)
        self._seed: int | None = None

    def _obs(self, obs: np.ndarray) -> torch.Tensor:
        return torch.tensor(obs, dtype=self._obs_dtype)  # a copy: a vector env made with copy=False reuses its array

    def _step(self, tensordict: TensorDictBase) -> TensorDictBase:
        obs, reward, terminated, truncated, info = self._vec.step(tensordict.get("action").numpy())
        self._last_obs = obs
        done = terminated | truncated
        self._ended = done
        if done.any():  # the episode's last observation, not the reset one gymnasium put in its place
            obs = obs.copy()
            obs[done] = np.stack(info["final_obs"][done])
        n = self.batch_size
        return TensorDict({"observation": self._obs(obs),
                           "reward": torch.as_tensor(reward, dtype=torch.float32).reshape(*n, 1),
                           "done": torch.as_tensor(done).reshape(*n, 1),
                           "terminated": torch.as_tensor(terminated).reshape(*n, 1),
                           "truncated": torch.as_tensor(truncated).reshape(*n, 1)}, batch_size=n)

    def _reset(self, tensordict: TensorDictBase | None = None, **kwargs) -> TensorDictBase:
        mask = None if tensordict is None else tensordict.get("_reset", None)
        if mask is None or self._last_obs is None:
            obs, _ = self._vec.reset(seed=self._seed)
            self._seed, self._ended = None, np.zeros(self.batch_size[0], dtype=bool)
        else:  # the envs that ended in the last step are reset already (SAME_STEP); reset only the others asked for
            mask = mask.reshape(-1).numpy()
            others = mask & ~self._ended
            obs = self._vec.reset(options={"reset_mask": others})[0] if others.any() else self._last_obs
            self._ended = self._ended & ~mask
        self._last_obs = obs
        n = self.batch_size
        false = torch.zeros(*n, 1, dtype=torch.bool)
        return TensorDict({"observation": self._obs(obs), "done": false, "terminated": false.clone(),
                           "truncated": false.clone()}, batch_size=n)

    def _set_seed(self, seed: int | None) -> None:
        self._seed = seed  # gymnasium seeds a vector env through reset (copy i: seed + i)
        self.reset()
