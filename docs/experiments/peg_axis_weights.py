"""What a learned policy does on each axis during the peg's insertion, and where its insertion time goes.

    python docs/experiments/peg_axis_weights.py POLICY [--seed 1] [--trials 8]

Runs the first `--trials` trials of `a3cqp evaluate --scene peg_in_hole --seed S` (the same trial seeds) with the
policy alone, then prints each trial's insertion time split into first contact -> tip 1 mm inside the bore and
1 mm -> success (20 mm), the mean f_d on z, and per local axis x, y, z the mean weights (w1 IK, w2 AC, w3 FC) and
mean |f_env| over the periods between the first contact and the success. docs/panda.md, section "Why IK only passes
the wrist's limit on the peg, what the reward's f_d cost decides", has the numbers.
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
    ap.add_argument("policy", type=Path)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--trials", type=int, default=8)
    args = ap.parse_args()
    logging.getLogger("a3cqp_rl.control.controller").setLevel(logging.ERROR)
    cfg = load_config(ROOT / "configs" / "panda_peg_in_hole.yaml")
    n = args.trials
    seeds = trial_seeds(args.seed, n)
    env, policy = PandaEnv(n, cfg, scene="peg_in_hole", trial_seeds=seeds), load_policy(args.policy)
    sc = env.scene
    td, done = env.reset(), np.zeros(n, dtype=bool)
    entered = np.full(n, np.nan)
    weights, forces, f_d = [], [], []
    while not done.all():
        td["action"] = policy(td["observation"])
        td = env.step(td)["next"]
        inserting = (sc.phase == sc.INSERT) & np.isfinite(sc.contact_time[:, 0]) & np.isnan(sc.success_time[:, 0])
        inserting &= ~done
        if inserting.any():
            weights.append(env.weights[inserting, :3])
            forces.append(np.abs(td["f_env_local"].numpy()[inserting, :3]))
            f_d.append(env.f_d[inserting, 2])
        in_bore = (sc.phase == sc.INSERT) & (sc.depth(env.pos) > 0.001) & np.isnan(entered)
        in_bore &= np.linalg.norm(env.pos[:, :2] - sc.hole[:2], axis=1) < 0.5 * sc.cfg.hole_diameter
        entered[in_bore] = env.t[in_bore]
        new = td["done"].reshape(-1).numpy() & ~done
        env.park(np.flatnonzero(new))
        done |= new
    contact, success = sc.contact_time[:, 0], sc.success_time[:, 0]
    print(f"{args.policy}: insertion time {np.round(success - contact, 2)} s (mean {np.nanmean(success - contact):.2f})")
    print(f"  first contact -> 1 mm in the bore {np.round(entered - contact, 2)} s")
    print(f"  1 mm in the bore -> success       {np.round(success - entered, 2)} s")
    print(f"  mean f_d on z while inserting: {np.concatenate(f_d).mean():.1f} N")
    w, f = np.concatenate(weights), np.concatenate(forces)
    for a, name in enumerate("xyz"):
        print(f"  axis {name}: mean (w1, w2, w3) {np.round(w[:, a].mean(0), 2)}, mean |f_env| {f[:, a].mean():.1f} N")


if __name__ == "__main__":
    main()
