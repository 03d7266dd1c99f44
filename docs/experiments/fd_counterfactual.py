"""Counterfactual for the ḟd region: does forcing ḟd inside the Fig. 5 contact region change the return?

Runs a trained policy (OUT/policy.pt) on 2048 point-mass episodes three times: as learned, with ḟd forced to +1
inside the region (`a3cqp_rl.regions.FIG5_REGIONS["fd_desired_force_in_contact"]`, normalised; THR replaces its lower
|f_env| edge), and forced to −1; prints the mean return per scenario and the fraction of steps spent in the region.

    python docs/experiments/fd_counterfactual.py CONFIG RUN_DIR ['{"point_mass": {...}}'] [THR]
"""

from __future__ import annotations

import json
import sys

import torch

from a3cqp_rl.config import load_config
from a3cqp_rl.regions import FIG5_REGIONS
from algorithms.a2c import load_policy
from envs.point_mass import SCENARIOS, PointMassEnv


def in_box(obs: torch.Tensor, thr: float) -> torch.Tensor:
    """Whether normalised observations (|e|, |f_env|, |f_ope|) [N, 3] lie in the ḟd region, |f_env| from `thr`."""
    _, e_range, f_env_range, f_ope_range = FIG5_REGIONS["fd_desired_force_in_contact"]
    lows = torch.tensor([e_range[0], thr, f_ope_range[0]])
    highs = torch.tensor([e_range[1], f_env_range[1], f_ope_range[1]])
    return ((obs >= lows) & (obs <= highs)).all(-1)


def episode_returns(cfg, policy, force: float | None, thr: float, n: int = 2048, seed: int = 1):  # noqa: ANN001, ANN201
    """Mean return over n episodes (all, and per scenario) and the fraction of steps inside the region."""
    env = PointMassEnv(n, cfg, seed=seed)
    env.reset()
    step_fn, obs_fn = env.fused_functions()
    state, pending, schedule = env.fused_inputs()
    obs, total, scenario, inside = obs_fn(state), torch.zeros(n), state["scenario"].clone(), 0
    for _ in range(cfg.point_mass.episode_steps):
        action = policy(obs).clamp(-1, 1)
        region = in_box(obs, thr)
        inside += int(region.sum())
        if force is not None:
            action[region, 3] = force
        state, _, obs, reward, _, _ = step_fn(state, pending, schedule, action)
        total += reward
    per = {name: round(total[scenario == i].mean().item(), 2) for i, name in enumerate(SCENARIOS)
           if (scenario == i).any()}
    return round(total.mean().item(), 2), per, inside / (n * cfg.point_mass.episode_steps)


def main() -> None:
    """CLI: see the module docstring."""
    if len(sys.argv) < 3 or sys.argv[1] in ("-h", "--help"):
        print(__doc__)
        sys.exit(0 if sys.argv[1:2] in (["-h"], ["--help"]) else 2)
    torch.set_num_threads(1)
    config, run = sys.argv[1], sys.argv[2]
    cfg = load_config(config, json.loads(sys.argv[3]) if len(sys.argv) > 3 else {})
    thr = float(sys.argv[4]) if len(sys.argv) > 4 else 0.3
    policy = load_policy(f"{run}/policy.pt")
    for force in (None, 1.0, -1.0):
        print(f"fd forced to {force}:", *episode_returns(cfg, policy, force, thr))


if __name__ == "__main__":
    main()
