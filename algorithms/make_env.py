"""Build the TorchRL env a config names (`env:` / `a3cqp train --env`): a registered env or any gymnasium id.

Registered names are listed in `a3cqp_rl.config.ENV_FACTORIES` as "module:function" strings; each function takes
(cfg, num_envs, seed) and returns a seeded TorchRL EnvBase with batch_size [num_envs]. Any other name must be a
gymnasium id: it runs as ONE batched env, gymnasium's synchronous vector env of `num_envs` copies in-process (TorchRL's
`GymEnv(num_envs=...)` starts one process per copy, slower on small machines), as `envs.gym_vector.GymVectorEnv`
where its spaces are flat Boxes (the A2C's case) and through TorchRL's `GymWrapper` otherwise.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING

from a3cqp_rl.config import ENV_FACTORIES, ExperimentConfig

if TYPE_CHECKING:  # annotations only: torchrl is imported where an env is built
    from torchrl.envs import EnvBase

__all__ = ["make_env", "point_mass", "gym_env"]


def make_env(cfg: ExperimentConfig, num_envs: int | None = None, seed: int | None = None) -> EnvBase:
    """The env `cfg.env` names, with `num_envs` (default a2c.num_envs) copies, seeded with `seed` (default cfg.seed)."""
    num_envs = cfg.a2c.num_envs if num_envs is None else num_envs
    seed = cfg.seed if seed is None else seed
    if cfg.env in ENV_FACTORIES:
        module, func = ENV_FACTORIES[cfg.env].split(":")
        return getattr(importlib.import_module(module), func)(cfg, num_envs, seed)
    return gym_env(cfg.env, num_envs, seed)


def point_mass(cfg: ExperimentConfig, num_envs: int, seed: int) -> EnvBase:
    """PointMassEnv (eq. 35), natively batched, reset."""
    from envs.point_mass import PointMassEnv

    env = PointMassEnv(num_envs, cfg, seed=seed)
    env.reset()
    return env


def gym_env(env_id: str, num_envs: int, seed: int, torchrl_wrapper: bool = False) -> EnvBase:
    """gymnasium `env_id` × num_envs as one TorchRL env, batch_size [num_envs], seeded: `envs.gym_vector.GymVectorEnv`
    for 1-D float Box observations and actions, TorchRL's `GymWrapper` for any other spaces (or for every space with
    `torchrl_wrapper`: the baseline of `bench/pendulum.py`)."""
    import logging

    import gymnasium as gym
    from torchrl.envs import GymWrapper

    from envs.gym_vector import GymVectorEnv, supported

    # the final observation of an episode (for bootstrapping at truncation) comes with the step only in SAME_STEP mode
    vec = gym.make_vec(env_id, num_envs=num_envs, vectorization_mode="sync",
                       vector_kwargs={"autoreset_mode": gym.vector.AutoresetMode.SAME_STEP})
    # a Box observation is what the A2C reads, and composite spaces fail inside TorchRL's wrapper with its internals'
    # messages (a Dict observation only at the first episode end); discrete actions build, and the A2C names them
    obs_space, act_space = vec.single_observation_space, vec.single_action_space
    simple_actions = (gym.spaces.Box, gym.spaces.Discrete, gym.spaces.MultiDiscrete, gym.spaces.MultiBinary)
    for what, space, ok in (("observation", obs_space, isinstance(obs_space, gym.spaces.Box)),
                            ("action", act_space, isinstance(act_space, simple_actions))):
        if not ok:
            vec.close()
            hint = (" (flatten it: gymnasium.wrappers.FlattenObservation, registered under an id of its own)"
                    if what == "observation" else " (A2C here has a Gaussian policy: continuous Box actions)")
            raise ValueError(f"{env_id}: its {what} space is {type(space).__name__}; the A2C reads a Box {what}"
                             f"{hint}")
    if supported(vec) and not torchrl_wrapper:
        env = GymVectorEnv(vec)
    else:
        log = logging.getLogger("torchrl")
        level = log.level
        log.setLevel(logging.WARNING)  # GymWrapper logs its spec probing at INFO on every construction
        try:
            env = GymWrapper(vec)
        finally:
            log.setLevel(level)
    env.set_seed(seed)
    return env
