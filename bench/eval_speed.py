"""Closed-loop evaluation speed: 6 policies x 4 scenarios x 64 episodes in one batched call (envs.point_mass_eval).

Times `evaluate` on the five baselines plus a learned-size policy (a [64, 64] tanh MLP, random weights) and, as the
peer, the same policies stepped one episode at a time through the gymnasium env of the SB3 benchmark
(bench/point_mass_gym.py, the C point mass) on a few episodes, scaled to the same number of agent steps: episode-steps
per second of each, and their ratio, measured in this run (medians).

Usage: python bench/eval_speed.py [--quick] [--episodes N] [--repeats R]
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from a3cqp_rl.cli import help_summary


def _mlp_policy(seed: int = 0):
    gen = torch.Generator().manual_seed(seed)
    w1, w2, w3 = (torch.randn(a, b, generator=gen) / b**0.5 for a, b in ((64, 3), (64, 64), (4, 64)))

    def policy(obs):
        return (torch.tanh(torch.tanh(obs @ w1.T) @ w2.T) @ w3.T).clamp(-1.0, 1.0)

    return policy


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark; print seconds per evaluation, episode-steps/s and the ratio to the one-episode loop."""
    from envs.point_mass_eval import EVAL_SCENARIOS, baseline_policies, evaluate, scenario_config

    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--quick", action="store_true", help="one repeat, fewer peer episodes")
    p.add_argument("--episodes", type=int, default=64)
    p.add_argument("--repeats", type=int, default=3)
    args = p.parse_args(argv)
    torch.set_num_threads(1)
    repeats = 1 if args.quick else args.repeats
    policies = {"mlp": _mlp_policy(), **baseline_policies()}
    steps_per_eval = len(policies) * args.episodes * sum(s.point_mass["episode_steps"] for s in EVAL_SCENARIOS.values())
    evaluate(policies, episodes=2)  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        evaluate(policies, episodes=args.episodes, seed=0)
        times.append(time.perf_counter() - t0)
    batched = statistics.median(times)

    import sys
    from pathlib import Path

    sys.path.insert(0, str(Path(__file__).resolve().parent))
    from point_mass_gym import PointMassGym

    from a3cqp_rl.config import ExperimentConfig

    peer_eps = 1 if args.quick else 2
    peer_steps, t0 = 0, time.perf_counter()
    for sc in EVAL_SCENARIOS.values():
        env = PointMassGym(scenario_config(ExperimentConfig(), sc)) if sc.point_mass.get("operator_model") != "hand" \
            else None
        if env is None:  # the gym env steps the C point mass, which has the training ('push') operator only
            continue
        env.reset(seed=0)
        for policy in policies.values():
            for _ in range(peer_eps):
                obs, _ = env.reset(options={"w_logits": [0.0, 0.0, 0.0], "f_d": 0.0})
                done = False
                while not done:
                    a = policy(torch.from_numpy(obs).unsqueeze(0))[0].numpy()
                    obs, _, _, done, _ = env.step(a)
                    peer_steps += 1
    peer_rate = peer_steps / (time.perf_counter() - t0)
    rate = steps_per_eval / batched
    print(f"evaluate: {len(policies)} policies x {len(EVAL_SCENARIOS)} scenarios x {args.episodes} episodes "
          f"({steps_per_eval:,} episode-steps) in {batched:.2f} s (median of {repeats}): {rate:,.0f} episode-steps/s")
    print(f"one episode at a time (gym env, C step, the same policies; free and contact scenarios): "
          f"{peer_rate:,.0f} episode-steps/s")
    print(f"ratio: {rate / peer_rate:.1f}x")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
