"""Where a scripted controller's peg trial passes a joint limit: the 1 kHz trace around its worst excess.

    python docs/experiments/peg_limit_trace.py --trial 6 --controller ik [--seed 0] [--ddq-scale 3]

Runs one trial of `a3cqp evaluate --scene peg_in_hole --seed S` (trial k of its 26, the same trial seeds) alone,
with the scripted weights of `--controller` (ik, ik_fc, equal, vic), records every control period and prints the
40 ms before and after the period of the worst excess past a datasheet position limit: the joint, its position,
speed, commanded torque and the QP's q̈*, the sensed |f_env|, the arm's contacts, the tip relative to the hole (the
rim's centre), the tool's tilt from the hole axis and the reference's depth. `--ddq-scale` multiplies the controller's joint acceleration limits (the
deceleration its joint-limit rows may ask for). docs/panda.md, section "Why IK only passes the wrist's limit on the
peg" has the numbers.
"""
from __future__ import annotations

import argparse
import dataclasses
import logging
import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's a3cqp_rl/envs/algorithms

from a3cqp_rl.config import load_config
from a3cqp_rl.control import A3CQPController
from a3cqp_rl.robot import PANDA_LIMITS
from envs.panda import PandaEnv
from envs.panda_eval import _scripted, trial_seeds

ROOT = Path(__file__).resolve().parents[2]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trial", type=int, default=6, help="trial index among the seed's 26")
    ap.add_argument("--controller", default="ik", choices=("ik", "ik_fc", "equal", "vic"))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--ddq-scale", type=float, default=1.0)
    ap.add_argument("--seconds", type=float, default=25.0, help="simulated time at most")
    args = ap.parse_args()
    logging.getLogger("a3cqp_rl.control.controller").setLevel(logging.ERROR)
    cfg = load_config(ROOT / "configs" / "panda_peg_in_hole.yaml")
    seeds = trial_seeds(args.seed, 26)
    limits = dataclasses.replace(PANDA_LIMITS, ddq_max=tuple(args.ddq_scale * a for a in PANDA_LIMITS.ddq_max))

    def controller(n, model=None, config=None, options=None):  # noqa: ANN001, ANN202
        return A3CQPController(n, model=model, config=config, options=options, limits=limits)

    env = PandaEnv(1, cfg, scene="peg_in_hole", trial_seeds=[seeds[args.trial]], controller_factory=controller)
    step, rec = env.ctrl.step, []

    def recording_step(*a, **k):  # noqa: ANN002, ANN003, ANN202
        out = step(*a, **k)
        rec.append((env.sim.data.time, env.q[0].copy(), env.qd[0].copy(), out.tau[0].numpy().copy(), out.qdd[0].numpy().copy(),
                    np.linalg.norm(env.f_env[0, :3]), env.sim.ncon, env.pos[0].copy(), a[6][0].numpy().copy(),
                    np.degrees(np.arccos(np.clip(-env.rot[0, 2, 2], -1.0, 1.0))),
                    int(out.status[0]), bool(out.fallback[0])))
        return out

    env.ctrl.step = recording_step
    latched, since = np.zeros(1, bool), np.zeros(1)
    td = env.reset()
    while env.t[0] < args.seconds and not bool(td["done"].all()):
        W, f_d, scale, scripted = _scripted(env, [args.controller], 1, latched, since, 1.0)
        env.hold_weights(scripted, W, f_d)
        env.stiffness_scale[:] = scale
        td["action"] = torch.zeros(1, 6, 4)
        td = env.step(td)["next"]
    q = np.array([r[1] for r in rec])
    per = np.maximum(env._q_lo - q, q - env._q_hi)
    k, j = np.unravel_index(per.argmax(), per.shape)
    hole = env.scene.hole
    print(f"trial {args.trial}, {args.controller}: worst excess {1e3 * per[k, j]:.1f} mrad, joint {j + 1} at "
          f"t = {rec[k][0]:.3f} s (limit {env._q_lo[j]:.4f} .. {env._q_hi[j]:.4f} rad, speed limit "
          f"{PANDA_LIMITS.dq_max[j]} rad/s); inserted: {bool(np.isfinite(env.scene.success_time[0, 0]))}")
    print("t [s]   q [rad]  q̇ [rad/s]  τ [N m]  q̈* [rad/s²]  |f_env| [N]  contacts  tip − rim centre [mm]     "
          "tilt [deg]  reference depth [mm]  QP status")
    for r in rec[max(k - 40, 0):k + 41:4]:
        t, qq, qd, tau, qdd, fe, nc, pos, pos_d, tilt, st, fb = r
        print(f"{t:6.3f}  {qq[j]:7.4f}  {qd[j]:8.2f}  {tau[j]:7.2f}  {qdd[j]:9.1f}  {fe:10.1f}  {nc:8d}  "
              f"{np.array2string(1e3 * (pos - hole), precision=1, suppress_small=True):>24}  "
              f"{tilt:8.1f}  {1e3 * (hole[2] - pos_d[2]):8.1f}  {st}{' fallback' if fb else ''}")


if __name__ == "__main__":
    main()
