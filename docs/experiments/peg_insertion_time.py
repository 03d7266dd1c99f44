"""What sets the peg-in-hole insertion time: every trial of an evaluation seed, learned and IK + FC, step by step.

    python docs/experiments/peg_insertion_time.py --seed 1 [--trials 26] [--set panda.e_max_rot=0.5 ...] [--out F.npz]

Runs the trials of `a3cqp evaluate --scene peg_in_hole --trials N --seed S --controllers learned,ik_fc` (the same
trial seeds, one batch) and prints per trial: the first contact after the insertion phase began (tau_c, s), when the
reference reached the success depth (tau = descent_time + success_depth / insert_speed), when the tip entered the
bore (inside it, 1 mm below the rim), the insertion time and its split into "until the peg is in the bore" and "from
there to the success depth"; then the paired differences learned − IK + FC over the trials both insert. `--set`
overrides config values (dotted keys, YAML values). `--out` saves the per-step arrays ([T, n]) for further analysis.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's a3cqp_rl/envs/algorithms

import numpy as np
import torch
import yaml

from a3cqp_rl.config import config_from_dict, config_to_dict, load_config
from algorithms.a2c import load_policy
from envs.panda import PandaEnv
from envs.panda_eval import _scripted, trial_seeds


def _override(cfg, sets: list[str]):  # noqa: ANN001, ANN202
    d = config_to_dict(cfg)
    for s in sets:
        key, val = s.split("=", 1)
        node = d
        *path, last = key.split(".")
        for p in path:
            node = node[p]
        node[last] = yaml.safe_load(val)
    return config_from_dict(d, "<--set>")


def run(seed: int, trials: int, config: str, sets: list[str], policy_path: str | None,
        controllers: tuple[str, ...] = ("learned", "ik_fc")) -> dict[str, np.ndarray]:
    """Per-step arrays [T, n] of the batch (controller-major, as `a3cqp evaluate`) and the scene's metrics."""
    cfg = _override(load_config(config), sets)
    policy = load_policy(policy_path or cfg.panda.policy) if "learned" in controllers else None
    seeds = trial_seeds(seed, trials)
    env = PandaEnv(len(controllers) * trials, cfg, scene="peg_in_hole", trial_seeds=seeds * len(controllers))
    n = env.num_envs
    latched, since = np.zeros(n, dtype=bool), np.zeros(n)
    keys = ("phase", "tau", "depth", "xy_off", "tilt", "ref_depth", "ref_xy", "fz_env", "fxy_env", "fd_z", "w_z",
            "w1_xy", "w1_rot", "ez")
    rec = {k: [] for k in keys}
    td = env.reset()
    finished = np.zeros(n, dtype=bool)
    sc = env.scene
    hole = sc.hole
    while not finished.all():
        W, f_d, scale, scripted = _scripted(env, list(controllers), trials, latched, since, 1.0)
        env.hold_weights(scripted, W, f_d)
        env.stiffness_scale[:] = scale
        action = torch.zeros(n, 6, 4)
        if policy is not None:
            with torch.no_grad():
                action[~scripted] = policy(td["observation"][~scripted])
        td["action"] = action
        td = env.step(td)["next"]
        fe = td["f_env_local"].numpy()
        w = td["weights"].numpy()
        rec["phase"].append(sc.phase.copy())
        rec["tau"].append(env.t - sc.t0)
        rec["depth"].append(sc.depth(env.pos))
        rec["xy_off"].append(np.linalg.norm(env.pos[:, :2] - hole[:2], axis=1))
        rec["tilt"].append(np.arccos(np.clip(-env.rot[:, 2, 2], -1.0, 1.0)))
        rec["ref_depth"].append(hole[2] - sc.pos_d[:, 2])
        rec["ref_xy"].append(np.linalg.norm(sc.pos_d[:, :2] - hole[:2], axis=1))
        rec["fz_env"].append(fe[:, 2])
        rec["fxy_env"].append(np.hypot(fe[:, 0], fe[:, 1]))
        rec["fd_z"].append(td["f_d"].numpy()[:, 2])
        rec["w_z"].append(w[:, 2])
        rec["w1_xy"].append(w[:, :2, 0].mean(axis=1))
        rec["w1_rot"].append(w[:, 3:5, 0].mean(axis=1))
        rec["ez"].append(td["e_local"].numpy()[:, 2])
        finished |= td["done"].reshape(n).numpy()
    out = {k: np.stack(v, 0).astype(np.float32) for k, v in rec.items()}
    out["time"] = (np.arange(len(rec["tau"])) + 1) * env.adapt.dt
    for k, v in sc.metrics().items():
        out["m_" + k] = np.asarray(v)[:, 0]
    out["controllers"] = np.array(controllers)
    out["trials"] = np.array(trials)
    out["seed"] = np.array(seed)
    out["descent_time"] = np.array(cfg.panda.peg_in_hole.descent_time)
    out["ref_success_tau"] = np.array(cfg.panda.peg_in_hole.descent_time
                                      + cfg.panda.peg_in_hole.success_depth / cfg.panda.peg_in_hole.insert_speed)
    return out


def per_trial(R: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Per arm [n]: contact tau, tau at which the tip entered the bore (inside, 1 mm deep), success tau, insertion
    time, and means of f_d, the z weights and the lateral w1 between contact and success."""
    ins = R["phase"] == 2
    n = R["phase"].shape[1]
    time = R["time"]
    t_start = np.array([time[np.argmax(ins[:, a])] - R["tau"][np.argmax(ins[:, a]), a] for a in range(n)])
    tau_c = R["m_contact_time"] - t_start
    tau_s = R["m_contact_time"] + R["m_insertion_time"] - t_start
    inside = ins & (R["xy_off"] < 0.01025) & (R["depth"] > 0.001)
    tau_in = np.where(inside.any(0), time[np.argmax(inside, 0)] - t_start, np.nan)
    between = ins & (time[:, None] - t_start[None] >= tau_c[None]) & (time[:, None] - t_start[None] <= tau_s[None])
    cnt = np.maximum(between.sum(0), 1)

    def mean(x: np.ndarray) -> np.ndarray:
        return (np.where(between, x, 0.0)).sum(0) / cnt

    return {"tau_c": tau_c, "tau_in": tau_in, "tau_s": tau_s, "time": R["m_insertion_time"],
            "success": R["m_success"].astype(bool), "fd_z": mean(R["fd_z"]), "w1_z": mean(R["w_z"][..., 0]),
            "w3_z": mean(R["w_z"][..., 2]), "w1_xy": mean(R["w1_xy"]), "fz_env": mean(R["fz_env"]),
            "fxy_env": mean(R["fxy_env"]), "mis_mm": 1e3 * R["m_misalign_translation"]}


def report(R: dict[str, np.ndarray]) -> None:
    P = per_trial(R)
    ctrl = [str(c) for c in R["controllers"]]
    K = int(R["trials"])
    ref = float(R["ref_success_tau"])
    print(f"seed {int(R['seed'])}: the reference reaches the success depth at tau = {ref:.2f} s after the insertion "
          f"phase began")
    for j, c in enumerate(ctrl):
        sl = slice(j * K, (j + 1) * K)
        s, t = P["success"][sl], P["time"][sl]
        print(f"{c:8s} {s.sum()}/{K}  time {np.nanmean(np.where(s, t, np.nan)):.3f} ± "
              f"{np.nanstd(np.where(s, t, np.nan), ddof=1):.2f} (median {np.nanmedian(np.where(s, t, np.nan)):.2f})  "
              f"tau_c {np.nanmean(P['tau_c'][sl]):.2f}  tau_in {np.nanmean(P['tau_in'][sl]):.2f}  "
              f"tau_s {np.nanmean(np.where(s, P['tau_s'][sl], np.nan)):.2f}  in->success "
              f"{np.nanmean(np.where(s, P['tau_s'][sl] - P['tau_in'][sl], np.nan)):.2f}  fd_z {P['fd_z'][sl].mean():.1f}"
              f"  w_z ({P['w1_z'][sl].mean():.2f}, -, {P['w3_z'][sl].mean():.2f})  w1_xy {P['w1_xy'][sl].mean():.2f}"
              f"  fz_env {P['fz_env'][sl].mean():.1f}  fxy_env {P['fxy_env'][sl].mean():.1f}")
    if len(ctrl) >= 2:
        a, b = slice(0, K), slice(K, 2 * K)
        both = P["success"][a] & P["success"][b]
        d = P["time"][a][both] - P["time"][b][both]
        print(f"paired {ctrl[0]} − {ctrl[1]} over {both.sum()} trials both insert: mean {d.mean():+.3f} s, median "
              f"{np.median(d):+.3f} s, {np.sum(d < 0)} faster / {np.sum(d > 0)} slower; split: contact "
              f"{np.nanmean(P['tau_c'][a][both] - P['tau_c'][b][both]):+.3f}, into the bore "
              f"{np.nanmean((P['tau_in'] - P['tau_c'])[a][both] - (P['tau_in'] - P['tau_c'])[b][both]):+.3f}, bore to "
              f"success {np.nanmean((P['tau_s'] - P['tau_in'])[a][both] - (P['tau_s'] - P['tau_in'])[b][both]):+.3f}")
        print(" k  mis[mm]  " + "  ".join(f"{c}: time (tau_c, tau_in, tau_s) fd_z" for c in ctrl[:2]))
        for k in range(K):
            row = []
            for arm in (k, K + k):
                row.append(f"{P['time'][arm]:5.2f}{'' if P['success'][arm] else '!'} ({P['tau_c'][arm]:.2f}, "
                           f"{P['tau_in'][arm]:.2f}, {P['tau_s'][arm]:.2f}) {P['fd_z'][arm]:4.1f}")
            print(f"{k:2d} {P['mis_mm'][k]:6.1f}   " + "   ".join(row))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--trials", type=int, default=26)
    ap.add_argument("--config", default="configs/panda_peg_in_hole.yaml")
    ap.add_argument("--policy", default=None)
    ap.add_argument("--controllers", default="learned,ik_fc")
    ap.add_argument("--set", action="append", default=[], help="dotted.key=value (YAML), repeatable")
    ap.add_argument("--out", default=None, help="save the per-step arrays (.npz)")
    ap.add_argument("--load", default=None, help="report a saved .npz instead of running")
    a = ap.parse_args()
    if a.load:
        R = dict(np.load(a.load))
    else:
        R = run(a.seed, a.trials, a.config, a.set, a.policy, tuple(a.controllers.split(",")))
        if a.out:
            Path(a.out).parent.mkdir(parents=True, exist_ok=True)
            np.savez_compressed(a.out, **R)
    report(R)


if __name__ == "__main__":
    main()
