"""Pendulum-v1: our A2C (configs/pendulum_a2c.yaml) next to Stable-Baselines3 A2C with the same settings, one run.

Speed: both train on gymnasium's Pendulum-v1 with the config's hyper-parameters (16 envs × 8 steps per update,
RMSProp, GAE 0.9, γ 0.9, advantages normalised, [64, 64] tanh MLPs), `torch.set_num_threads(1)`, for N agent steps;
the two alternate R times and medians are reported. Only SB3's `learn()` is timed (construction excluded); ours is
`algorithms.a2c.train(cfg, None, total_steps=N)`'s steps/s (compile time excluded, shown separately).
  - SB3: `A2C("MlpPolicy", make_vec_env("Pendulum-v1", n_envs), ...)`: a DummyVecEnv, actions clipped to [-2, 2].
  - ours: gymnasium's synchronous vector env as `envs.gym_vector.GymVectorEnv`, a TorchRL Collector, the
    hand-derived update; and the same trainer on TorchRL's `GymWrapper` around the same vector env (what
    `algorithms.make_env.gym_env` used before GymVectorEnv), the baseline of the env's cost.
Learning (`--learn`): trains the config for its 1e6 steps on each seed and evaluates the final policy
deterministically (the mean action) on 20 fresh episodes per seed (seeds 1000 + s): a random policy scores about
−1200 per episode, the config's target is −400 or better.

Usage: python bench/pendulum.py [--steps N] [--repeats R] [--quick] [--learn] [--seeds 0,1,2]
"""

from __future__ import annotations

import argparse
import os
import statistics
import sys
import time
from pathlib import Path

from a3cqp_rl.cli import help_summary

_ROOT = Path(__file__).resolve().parent.parent
CONFIG = _ROOT / "configs" / "pendulum_a2c.yaml"


def sb3_kwargs(cfg) -> dict:
    """SB3 A2C arguments equal to the config's A2C settings."""
    a = cfg.a2c
    return dict(learning_rate=a.learning_rate, n_steps=a.n_steps, gamma=a.gamma, gae_lambda=a.gae_lambda,
                ent_coef=a.ent_coef, vf_coef=a.vf_coef, max_grad_norm=a.max_grad_norm, rms_prop_eps=a.rms_eps,
                use_rms_prop=True, normalize_advantage=a.normalize_advantage, device="cpu", seed=cfg.seed,
                policy_kwargs=dict(log_std_init=a.log_std_init, net_arch=dict(pi=list(a.hidden), vf=list(a.hidden))))


def run_sb3(cfg, steps: int) -> float:
    """SB3 A2C steps/s of `learn(steps)` on Pendulum-v1 with the config's settings."""
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.logger import Logger

    env = make_vec_env("Pendulum-v1", n_envs=cfg.a2c.num_envs, seed=cfg.seed)
    try:
        model = A2C("MlpPolicy", env, **sb3_kwargs(cfg))
        # no folder: SB3's default logger makes an empty <tempdir>/SB3-<date> folder at every learn()
        model.set_logger(Logger(None, []))
        t0 = time.perf_counter()
        model.learn(total_timesteps=steps)
        return model.num_timesteps / (time.perf_counter() - t0)
    finally:
        env.close()


def run_ours(cfg, steps: int, wrapper: bool = False) -> tuple[float, float, dict]:
    """Our steps/s (compile excluded), compile seconds and the loop's timing blocks; `wrapper`: on TorchRL's
    GymWrapper instead of GymVectorEnv."""
    from algorithms.a2c import train
    from algorithms.make_env import gym_env

    env = gym_env("Pendulum-v1", cfg.a2c.num_envs, cfg.seed, torchrl_wrapper=True) if wrapper else None
    res = train(cfg, None, total_steps=steps, env=env)
    return res.steps_per_second, res.compile_seconds, res.timings


def evaluate(policy_path: Path, seed: int, episodes: int = 20) -> float:
    """Mean return of the policy's mean action over `episodes` fresh Pendulum-v1 episodes (seeded 1000 + seed)."""
    from algorithms.make_env import gym_env
    from algorithms.policy import first_episode_returns

    return float(first_episode_returns(policy_path, gym_env("Pendulum-v1", episodes, seed=1000 + seed), 200).mean())


def learn(cfg_path: Path, seeds: list[int], out: Path) -> None:
    """Train the config for its total steps on each seed; print training and evaluation returns."""
    from a3cqp_rl.config import load_config
    from algorithms.a2c import train

    print(f"learning check: {cfg_path.name}, seeds {seeds}, deterministic evaluation on 20 episodes per seed")
    scores = []
    for s in seeds:
        cfg = load_config(cfg_path, {"seed": s})
        res = train(cfg, out / f"seed_{s}", total_steps=cfg.a2c.total_steps, force=True)
        score = evaluate(res.policy_path, s)
        scores.append(score)
        print(f"  seed {s}: {res.steps:,} steps in {res.seconds:.0f} s ({res.steps_per_second:,.0f} steps/s); "
              f"last 100 training episodes {res.final_metrics['episode_reward']:.0f}; evaluation {score:.0f}", flush=True)
    print(f"  -400 or better on {sum(v >= -400 for v in scores)} of {len(scores)} seeds (mean {statistics.mean(scores):.0f})")


def main(argv: list[str] | None = None) -> int:
    """Print steps/s of SB3 and ours, their ratio, and with --learn the learning check; returns 0."""
    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--steps", type=int, default=None, help="agent steps per timed run (default 40000; 8000 --quick)")
    p.add_argument("--repeats", type=int, default=None, help="runs of each (default 3; 1 with --quick)")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--learn", action="store_true", help="also train 1e6 steps per seed and evaluate")
    p.add_argument("--seeds", default="0,1,2", help="seeds of the learning check")
    p.add_argument("--config", default=str(CONFIG))
    p.add_argument("--out", default="runs/bench_pendulum", help="run folders of the learning check")
    args = p.parse_args(argv)
    steps = args.steps or (8000 if args.quick else 40000)
    repeats = args.repeats or (1 if args.quick else 3)

    import torch

    from a3cqp_rl.config import load_config

    torch.set_num_threads(1)
    cfg = load_config(args.config, {"a2c": {"region_checks": 0}})
    try:
        import stable_baselines3

        sb3_version = stable_baselines3.__version__
    except ImportError:
        sb3_version = None
        print("stable-baselines3 is not installed (the 'bench' extra): only our side runs")
    a = cfg.a2c
    print(f"Pendulum-v1, {a.num_envs} envs x n={a.n_steps} per update, {steps:,} steps per run, {repeats} run(s) "
          f"each (median); torch threads 1, {os.cpu_count()} cores, load {os.getloadavg()[0]:.2f}; "
          f"stable-baselines3 {sb3_version}, torch {torch.__version__}, python {sys.version.split()[0]}")
    sb3, ours, wrapped, compile_s, blocks = [], [], [], [], {}
    for i in range(repeats):
        if sb3_version:
            sb3.append(run_sb3(cfg, steps))
            print(f"  run {i + 1}: SB3  {sb3[-1]:>8,.0f} steps/s", flush=True)
        rate, comp, blocks = run_ours(cfg, steps)
        ours.append(rate)
        compile_s.append(comp)
        print(f"  run {i + 1}: ours {rate:>8,.0f} steps/s (+ {comp:.1f} s compiling; "
              + ", ".join(f"{k} {v:.2f} s" for k, v in blocks.items()) + ")", flush=True)
        wrapped.append(run_ours(cfg, steps, wrapper=True)[0])
        print(f"  run {i + 1}: ours on GymWrapper {wrapped[-1]:>8,.0f} steps/s", flush=True)
    print(f"{'trainer':<44} {'steps/s':>9} {'1e6 steps':>10}")
    for name, rates in (("SB3 A2C (MlpPolicy, DummyVecEnv)", sb3), ("ours (algorithms.a2c.train, Collector)", ours),
                        ("ours on TorchRL's GymWrapper", wrapped)):
        if rates:
            print(f"{name:<44} {statistics.median(rates):>9,.0f} {1e6 / statistics.median(rates) / 60:>8.1f} min")
    if sb3:
        print(f"ratio ours/SB3 (median steps/s): {statistics.median(ours) / statistics.median(sb3):.2f}x")
    print(f"ratio GymVectorEnv/GymWrapper (median steps/s): {statistics.median(ours) / statistics.median(wrapped):.2f}x")
    if args.learn:
        learn(Path(args.config), [int(s) for s in args.seeds.split(",")], Path(args.out))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
