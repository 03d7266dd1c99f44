"""Why some learned peg-in-hole trials are slow: chosen trials of an evaluation seed, learned and IK + FC side by side.

    python docs/experiments/peg_slow_trials.py --seed 4 --trials 26 --pick 3,17 [--out runs/s4_slow]

Runs trials `--pick` of `a3cqp evaluate --scene peg_in_hole --trials N --seed S` (the same trial seeds) for the
learned controller and IK + FC in one batch, and prints, every 0.5 s from first contact to success: the tip's
lateral distance to the hole axis and the x-y reference's, its depth below the rim, the tool's tilt, f_env along
and across the tool axis, the policy's weights (w1, w2, w3) and f_d on z of L, and w1 across. `--out` also writes one run folder per trial
(episode_learned.npz, episode_ik_fc.npz) for `a3cqp plot episode`.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's a3cqp_rl/envs/algorithms

import numpy as np
import torch

from a3cqp_rl.config import load_config
from algorithms.a2c import load_policy
from envs.panda import PandaEnv
from envs.panda_eval import RECORD_KEYS, _scripted, trial_seeds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=4)
    ap.add_argument("--trials", type=int, default=26, help="N of the evaluation whose trial seeds are used")
    ap.add_argument("--pick", required=True, help="comma-separated trial indices")
    ap.add_argument("--policy", default=None, help="default: the config's panda.policy")
    ap.add_argument("--config", default="configs/panda_peg_in_hole.yaml")
    ap.add_argument("--out", default=None)
    a = ap.parse_args()
    cfg = load_config(a.config)
    policy = load_policy(a.policy or cfg.panda.policy)
    pick = [int(k) for k in a.pick.split(",")]
    seeds = trial_seeds(a.seed, a.trials)
    seeds = [seeds[k] for k in pick]
    controllers = ["learned", "ik_fc"]
    k = len(pick)
    env = PandaEnv(2 * k, cfg, scene="peg_in_hole", trial_seeds=seeds * 2)
    n = env.num_envs
    latched, since = np.zeros(n, dtype=bool), np.zeros(n)
    keys = RECORD_KEYS + env.signal_keys
    rec = {key: [] for key in keys + ("tilt_deg", "xy_off_mm", "ref_off_mm", "q")}
    td = env.reset()
    finished = np.zeros(n, dtype=bool)
    hole = np.array(cfg.panda.peg_in_hole.hole_center)
    while not finished.all():
        W, f_d, scale, scripted = _scripted(env, controllers, k, latched, since, 1.0)
        env.hold_weights(scripted, W, f_d)
        env.stiffness_scale[:] = scale
        action = torch.zeros(n, 6, 4)
        with torch.no_grad():
            action[~scripted] = policy(td["observation"][~scripted])
        td["action"] = action
        td = env.step(td)["next"]
        for key in keys:
            rec[key].append(td[key].numpy().copy())
        pos, rot = env.pos, env.rot
        rec["q"].append(env.q.copy())
        rec["xy_off_mm"].append(1e3 * np.linalg.norm(pos[:, :2] - hole, axis=1))
        rec["ref_off_mm"].append(1e3 * np.linalg.norm(env.scene.pos_d[:, :2] - hole, axis=1))
        rec["tilt_deg"].append(np.degrees(np.arccos(np.clip(-rot[:, 2, 2], -1.0, 1.0))))
        finished |= td["done"].reshape(n).numpy()
    R = {key: np.stack(v, 0) for key, v in rec.items()}  # [T, n, ...]
    m = env.scene.metrics()
    for j, trial in enumerate(pick):
        print(f"\n=== seed {a.seed} trial {trial}: misalignment at contact "
              f"{1e3 * m['misalign_translation'][j, 0]:.1f} mm, {np.degrees(m['misalign_rotation'][j, 0]):.2f} deg")
        for c, arm in (("learned", j), ("ik_fc", k + j)):
            t0 = m["contact_time"][arm, 0]
            print(f"--- {c}: success {bool(m['success'][arm, 0])}, insertion time {m['insertion_time'][arm, 0]:.2f} s, "
                  f"extracted {bool(m['extracted'][arm, 0])}")
            print("  t-t0   xy[mm] ref[mm] depth[mm] tilt  fz_env |fxy_env|  w_z(w1,w2,w3)    fd_z  w1_x  w1_y  phase")
            t = R["time"][:, arm]
            for tt in np.arange(0.0, 16.0, 0.5):
                i = np.searchsorted(t, t0 + tt)
                if i >= len(t) or R["phase"][i, arm] > 2:
                    break
                fe = R["f_env_local"][i, arm]
                w = R["weights"][i, arm]
                print(f"  {tt:4.1f} {R['xy_off_mm'][i, arm]:7.2f} {R['ref_off_mm'][i, arm]:7.2f} "
                      f"{1e3 * R['depth'][i, arm]:8.2f} "
                      f"{R['tilt_deg'][i, arm]:5.2f} {fe[2]:7.2f} {np.hypot(fe[0], fe[1]):7.2f}  "
                      f"({w[2, 0]:.2f},{w[2, 1]:.2f},{w[2, 2]:.2f}) {R['f_d'][i, arm, 2]:6.2f} "
                      f"{w[0, 0]:.2f}  {w[1, 0]:.2f}  {int(R['phase'][i, arm])}")
        if a.out:
            out = Path(a.out) / f"trial{trial}"
            out.mkdir(parents=True, exist_ok=True)
            meta = {"scene": env.scene.name, "tool": env.scene.tool, "scene_xml": env.scene.mjcf(),
                    "phase_names": np.array(env.scene.phase_names), "phase_task": np.array(env.scene.phase_task)}
            for c, arm in (("learned", j), ("ik_fc", k + j)):
                last = int(np.argmax(R["phase"][:, arm] == len(env.scene.phase_names) - 1)) or len(R["time"])
                ep = {key: R[key][: last + 1, arm] for key in keys + ("q",)}
                np.savez_compressed(out / f"episode_{c}.npz", **ep, **meta)


if __name__ == "__main__":
    main()
