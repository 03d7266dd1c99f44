"""How the operator's hand and the learned policy approach one guidance waypoint, every 0.5 s.

    python docs/experiments/guidance_waypoint_trace.py [--config configs/panda_guidance.yaml] [--arm 0] [--waypoint 1]

Runs the first four trials of `a3cqp evaluate --scene guidance` (seed 0) with the learned policy alone and prints,
for one arm while the operator guides it to one waypoint: the hand's offset from its goal (arm frame, mm), the
operator's force on the handle (N, arm frame), the observed f_ope (local frame L), f_d and the weights (w1 IK, w2
admittance, w3 force control) of x, y and z of L. docs/panda.md, section "Stiff end stops, ...", has the numbers.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # this checkout's a3cqp_rl/envs/algorithms

from a3cqp_rl.config import load_config
from algorithms.a2c import load_policy
from envs.panda import PandaEnv
from envs.panda_eval import trial_seeds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--config", type=Path, default=ROOT / "configs" / "panda_guidance.yaml")
    ap.add_argument("--arm", type=int, default=0, help="trial 0-3")
    ap.add_argument("--waypoint", type=int, default=1, help="0-based")
    args = ap.parse_args()
    logging.getLogger("a3cqp_rl.control.controller").setLevel(logging.ERROR)
    cfg = load_config(args.config)
    n, a = 4, args.arm
    env = PandaEnv(n, cfg, scene="guidance", trial_seeds=trial_seeds(0, n))
    policy = load_policy(ROOT / cfg.panda.policy)
    sc, op = env.scene, env.operator
    td, done, t0 = env.reset(), np.zeros(n, dtype=bool), None
    while not done.all():
        td["action"] = policy(td["observation"])
        td = env.step(td)["next"]
        done |= td["done"].reshape(-1).numpy()
        if sc.phase[a] != sc.GUIDE or sc.k[a] != args.waypoint:
            continue
        t0 = env.t[a] if t0 is None else t0
        if round((env.t[a] - t0) / env.adapt.dt) % 50:
            continue
        off = 1e3 * (env.pos[a] + env.rot[a] @ env._o_handle - op.goal[a])
        print(f"t {env.t[a] - t0:4.1f} s  hand - goal {np.round(off, 1)} mm  operator force "
              f"{np.round(env.handle_force[a], 1)} N  f_ope (L) {np.round(td['f_ope_local'].numpy()[a, :3], 1)} N  "
              f"f_d {np.round(env.f_d[a, :3], 1)} N  w x, y, z {np.round(env.weights[a, :3], 2).tolist()}")


if __name__ == "__main__":
    main()
