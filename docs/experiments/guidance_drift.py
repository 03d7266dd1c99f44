"""Why the learned controller drifts from the taught pose in the free-guidance scene: per-axis weights, pose error,
f*, f_adm and tool speed after each release, for a given task blend.

    python docs/experiments/guidance_drift.py [--blend eq35|eq24] [--idle-force free|damps|holds] [--trials 4]

Prints the largest drift per trial and waypoint, then trial 0 after its first release every 0.1 s: distance to the
taught pose, its local components, the tool velocity, the policy's w1 and w2 per translational axis of L, the
controller's w1 (after `panda.idle_force`), and f*, f_adm, f_ext in L.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's a3cqp_rl/envs/algorithms

import numpy as np
import torch

from a3cqp_rl.config import config_from_dict, config_to_dict, load_config
from algorithms.a2c import load_policy
from envs.panda import PandaEnv, to_local
from envs.panda_eval import trial_seeds


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--blend", default=None, help="panda.task_blend (default: the config's)")
    ap.add_argument("--idle-force", default=None, help="panda.idle_force (default: the config's)")
    ap.add_argument("--trials", type=int, default=4)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--policy", default="policies/point_mass_fig5_fd_1e6_seed0.pt")
    ap.add_argument("--config", default="configs/panda_guidance.yaml")
    a = ap.parse_args()
    cfg = load_config(a.config)
    d = config_to_dict(cfg)
    d["panda"]["task_blend"] = a.blend or d["panda"]["task_blend"]
    d["panda"]["idle_force"] = a.idle_force or d["panda"]["idle_force"]
    cfg = config_from_dict(d, "<options>")
    policy = load_policy(a.policy)
    seeds = trial_seeds(a.seed, a.trials)
    env = PandaEnv(a.trials, cfg, scene="guidance", trial_seeds=seeds)
    last = {}
    step = env.ctrl.step

    def spy(*args, **kw):  # noqa: ANN002, ANN003, ANN202
        out = step(*args, **kw)
        last["f"], last["f_adm"] = out.wrench.numpy().copy(), out.f_adm.numpy().copy()
        return out

    env.ctrl.step = spy
    td = env.reset()
    sc = env.scene
    rows = []  # per arm in a pause after a release: the quantities printed below
    prev_phase = sc.phase.copy()
    t_rel = np.full(a.trials, np.nan)
    prev_pos = env.pos.copy()
    while not td["done"].all():
        with torch.no_grad():
            td["action"] = policy(td["observation"])
        td = env.step(td)["next"]
        ph = sc.phase.copy()
        t_rel[(ph == sc.PAUSE) & (prev_phase == sc.GUIDE)] = env.t[(ph == sc.PAUSE) & (prev_phase == sc.GUIDE)]
        prev_phase = ph
        for i in np.flatnonzero((ph == sc.PAUSE) & (sc.k > 0)):
            dt = env.t[i] - t_rel[i]
            e = np.linalg.norm(env.pos[i] - sc.pos_d[i]) * 1e3
            f_l = to_local(env.rot[i:i + 1], last["f"][i:i + 1])[0]
            fa_l = to_local(env.rot[i:i + 1], last["f_adm"][i:i + 1])[0]
            v = to_local(env.rot[i:i + 1], np.concatenate([env.pos[i] - prev_pos[i], np.zeros(3)])[None])[0, :3] / env.adapt.dt
            eL = to_local(env.rot[i:i + 1], np.concatenate([env.pos[i] - sc.pos_d[i], np.zeros(3)])[None])[0, :3]
            wc = env.controller_weights()[0][i, :3, 0]
            rows.append((i, int(sc.k[i]), dt, e, env.weights[i, :3].copy(), wc, f_l[:3], fa_l[:3], v, eL,
                         to_local(env.rot[i:i + 1], env.f_ext[i:i + 1])[0, :3]))
        prev_pos = env.pos.copy()
    np.set_printoptions(precision=2, suppress=True)
    print(f"task_blend={cfg.panda.task_blend} state_leak={cfg.panda.state_leak} idle_force={cfg.panda.idle_force}")
    print("drift per trial and waypoint [mm]:\n", sc.metrics()["drift"] * 1e3)
    for r in rows:
        i, k, dt, e, w, wc, f, fa, v, eL, fx = r
        if i == 0 and k == 1 and dt < 1.0 and (abs(dt - round(dt / 0.1) * 0.1) < 5e-3):
            print(f"t+{dt:4.2f}s |x-x_d|={e:5.1f}mm x-x_d(L)={eL*1e3} v(L)={v*1e3} mm/s w1={w[:, 0]} w2={w[:, 1]} ctrl w1={wc} "
                  f"f*={f} f_adm={fa} f_ext={fx}")


if __name__ == "__main__":
    main()
