"""How far a joint goes past its datasheet limit under random held actions (the slow test's loop), per seed.

    python docs/experiments/joint_limit_excess.py --seeds 1-6 [--steps 3000] [--q-margin 0.05] [--include-f-ext]

The loop of `tests/test_panda_env.py::test_joint_and_torque_limits_hold_over_many_random_episodes`: 8 arms on
peg-in-hole (3-s trials, the operator on), random actions held for 20 agent steps, done arms reset. Prints per seed
the worst excess past a datasheet position limit [mrad], its joint and arm, the largest |τ|/τ_max and the QP
fallbacks (1 kHz periods of one arm that braked because the QP failed). `--q-margin` sets
ControllerOptions.q_margin (default 0.01 rad), `--include-f-ext` ControllerOptions.joint_limits_include_f_ext.
docs/panda.md, section "Joint limits under random weights, contact dropouts, and the runs that yield", has the numbers.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's a3cqp_rl/envs/algorithms

import numpy as np
import torch

from a3cqp_rl.config import config_from_dict
from a3cqp_rl.control import ControllerOptions
from a3cqp_rl.robot import PANDA_LIMITS
from algorithms.train import parse_seeds
from envs.panda import PandaEnv

ARMS = 8


def excess(seed: int, steps: int, options: ControllerOptions) -> tuple[float, int, int, float, int]:
    """(worst excess [rad], its joint, its arm, max |τ|/τ_max, QP fallback periods) of one seed's run."""
    # the test's shortened procedure (tests/test_panda_env.py, FAST_PEG) with 3-s trials
    cfg = config_from_dict({"panda": {"peg_in_hole": {"settle_time": 0.1, "approach_time": 1.0, "align_time": 3.0,
                                                      "time_limit": 3.0}}})
    env = PandaEnv(ARMS, cfg, seed=seed, controller_options=options)
    gen = torch.Generator().manual_seed(seed)
    q_min, q_max, tau_max = (np.array(v) for v in (PANDA_LIMITS.q_min, PANDA_LIMITS.q_max, PANDA_LIMITS.tau_max))
    worst, where, tau = -np.inf, (0, 0), 0.0
    td, action = env.reset(), torch.zeros(ARMS, 6, 4)
    for k in range(steps):
        if k % 20 == 0:
            action = torch.rand(ARMS, 6, 4, generator=gen) * 2 - 1
        td["action"] = action
        td = env.step(td)["next"]
        over = np.maximum(q_min - env.q, env.q - q_max)
        if over.max() > worst:
            worst, where = float(over.max()), np.unravel_index(int(over.argmax()), over.shape)
        tau = max(tau, float(np.max(np.abs(env.tau) / tau_max)))
        done = td["done"].reshape(ARMS)
        if done.any():
            td = env.reset(td.empty().set("_reset", done.reshape(ARMS, 1)))
    return worst, int(where[1]) + 1, int(where[0]), tau, env.ctrl.fallback_count


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=parse_seeds, default=[1, 2, 3], help="e.g. 1-6 or 1,3,5")
    ap.add_argument("--steps", type=int, default=3000, help="agent steps (10 ms each) per seed")
    ap.add_argument("--q-margin", type=float, default=ControllerOptions.q_margin)
    ap.add_argument("--include-f-ext", action="store_true")
    args = ap.parse_args()
    logging.getLogger("a3cqp_rl.control.controller").setLevel(logging.ERROR)  # one warning per fallback otherwise
    options = ControllerOptions(q_margin=args.q_margin, joint_limits_include_f_ext=args.include_f_ext)
    print(f"{ARMS} arms x {args.steps} agent steps, q_margin {args.q_margin} rad, include_f_ext {args.include_f_ext}")
    for seed in args.seeds:
        worst, joint, arm, tau, fallbacks = excess(seed, args.steps, options)
        print(f"seed {seed}: worst excess {1e3 * max(worst, 0.0):5.1f} mrad (joint {joint}, arm {arm}), "
              f"max |tau|/tau_max {tau:.3f}, QP fallback periods {fallbacks}")


if __name__ == "__main__":
    main()
