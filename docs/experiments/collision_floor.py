"""How far an exact contact pre-filter could still cut MuJoCo's collision pass in the peg-in-hole evaluation.

    python docs/experiments/collision_floor.py [--trials 13] [--seed 0] [--at 300 500 700 900 1100 1500]

Runs one worker's share of `a3cqp evaluate --scene peg_in_hole` (13 trials x 5 controllers = 65 arms, one process)
and, at the agent periods `--at` (10 control periods each), times `mj_collision` on the simulation's own state four
ways (median of 5 x 50 calls each, interleaved):

* none: the pre-filter's callback registered but dropping nothing (MuJoCo's midphase and narrow phase alone);
* cylinder: the shipped exact pre-filter (a3cqp_rl/robot/contact_filter.py);
* oracle: every bore box that makes no contact at that state switched off, on top of the pre-filter. No exact
  pre-filter can drop more than that, so this is the floor of any of them;
* no boxes: every bore box switched off (the arms' other geoms and the broad phase);
* contype only: the oracle's boxes given `geom_contype` 0 but their `geom_conaffinity` kept, which switches off
  nothing (MuJoCo pairs two geoms when either's contype meets the other's conaffinity: the peg's contype 2 still
  meets the boxes' conaffinity 2). An earlier probe switched the boxes off that way.

Each way must find the same contacts (asserted). docs/panda.md, section "The collision pass's floor under an exact
pre-filter", has the numbers.
"""
from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import mujoco
import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # this checkout's a3cqp_rl/envs/algorithms

import envs.panda as panda_env  # noqa: E402
from a3cqp_rl.config import load_config  # noqa: E402
from envs import panda_eval  # noqa: E402


class _Done(Exception):
    pass


def _median_us(f, calls: int = 50) -> float:  # noqa: ANN001
    times = []
    for _ in range(calls):
        t = time.perf_counter()
        f()
        times.append(time.perf_counter() - t)
    return float(np.median(times)) * 1e6


def _measure(env: panda_env.PandaEnv) -> str:
    """One line: live arms, contacts, boxes in contact, pre-filter pairs, and the four ways' µs per call."""
    sim = env.sim
    m, d, reg = sim.model, sim.data, sim._contact_filter
    role = reg.role  # read in place by contact_filter.c: zeroed, the callback drops nothing
    role0 = role.copy()
    boxes = np.flatnonzero(role0 == 2)
    mujoco.mj_collision(m, d)
    ncon = d.ncon
    touching = set(d.contact.geom[:ncon].ravel().tolist())
    idle = np.array([b for b in boxes if b not in touching], dtype=int)
    seen0, dropped0 = reg.counts()
    mujoco.mj_collision(m, d)
    seen, dropped = (a - b for a, b in zip(reg.counts(), (seen0, dropped0)))
    contype, conaffinity = m.geom_contype.copy(), m.geom_conaffinity.copy()
    spent: dict[str, list[float]] = {"none": [], "cylinder": [], "oracle": [], "no boxes": [], "contype only": []}
    found = set()

    def collide() -> None:
        mujoco.mj_collision(m, d)

    try:
        for _ in range(5):
            role[:] = 0
            spent["none"].append(_median_us(collide))
            found.add(d.ncon)
            role[:] = role0
            spent["cylinder"].append(_median_us(collide))
            found.add(d.ncon)
            m.geom_contype[idle], m.geom_conaffinity[idle] = 0, 0
            spent["oracle"].append(_median_us(collide))
            found.add(d.ncon)
            m.geom_contype[boxes], m.geom_conaffinity[boxes] = 0, 0
            spent["no boxes"].append(_median_us(collide))
            m.geom_contype[:], m.geom_conaffinity[:] = contype, conaffinity
            m.geom_contype[idle] = 0
            spent["contype only"].append(_median_us(collide))
            found.add(d.ncon)
            m.geom_contype[:] = contype
    finally:
        role[:] = role0
        m.geom_contype[:], m.geom_conaffinity[:] = contype, conaffinity
    mujoco.mj_collision(m, d)  # the state's own contacts back
    if found != {ncon} or d.ncon != ncon:
        raise AssertionError(f"the ways found different contacts: {sorted(found)} against {ncon}")
    times = " | ".join(f"{np.median(v):8.0f}" for v in spent.values())
    return (f"{int((~env.parked).sum()):4d} | {ncon:8d} | {len(boxes) - len(idle):15d} | {seen:5d} / {dropped:4d} "
            f"| {times}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=13)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--at", type=int, nargs="+", default=[300, 500, 700, 900, 1100, 1500],
                    help="agent periods (10 ms each) to measure at")
    args = ap.parse_args()
    torch.set_num_threads(1)
    cfg = load_config(ROOT / "configs" / "panda_peg_in_hole.yaml")
    step, count = panda_env.PandaEnv._step, [0]
    print("agent period | live arms | contacts | boxes in contact | pre-filter pairs seen / dropped | "
          "µs per mj_collision: none | cylinder | oracle | no boxes | contype only")

    def measured_step(env, td):  # noqa: ANN001, ANN202
        count[0] += 1
        if count[0] in args.at:
            print(f"{count[0]:12d} | {_measure(env)}", flush=True)
        if count[0] >= max(args.at):
            raise _Done
        return step(env, td)

    panda_env.PandaEnv._step = measured_step
    try:
        panda_eval._run_job(("peg_in_hole", cfg.panda.policy, panda_eval.trial_seeds(args.seed, args.trials), cfg,
                             panda_eval.CONTROLLERS, (), 1, False, None, True))
    except _Done:
        pass


if __name__ == "__main__":
    main()
