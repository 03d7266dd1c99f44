"""configs/pendulum_a2c.yaml learns gymnasium's Pendulum-v1 within its 1e6 steps (slow: ~1-2 min per seed)."""

from pathlib import Path

import pytest

from a3cqp_rl.config import load_config
from algorithms.a2c import train
from algorithms.make_env import gym_env
from algorithms.policy import first_episode_returns

CONFIG = Path(__file__).parents[1] / "configs" / "pendulum_a2c.yaml"


def test_pendulum_config_is_the_documented_task():
    cfg = load_config(CONFIG)
    assert cfg.env == "Pendulum-v1" and cfg.a2c.total_steps <= 1_000_000


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_pendulum_config_reaches_minus_400_within_1e6_steps(tmp_path, seed):
    cfg = load_config(CONFIG, {"seed": seed})
    res = train(cfg, tmp_path / "run")
    # the saved policy's mean action on 20 fresh episodes (a random policy scores about -1200)
    score = float(first_episode_returns(res.policy_path, gym_env("Pendulum-v1", 20, seed=1000 + seed), 200).mean())
    assert score >= -400, score
