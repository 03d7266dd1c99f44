"""Where the peg-in-hole evaluation's wall time goes: wall seconds per simulated second, with the parked arms.

    python docs/experiments/eval_timeline.py [--trials 13] [--seed 0] [--hole-segments 32] [--controllers ...]
                                             [--breakdown]

Runs one batched simulation of every controller on the trials of `--seed` (what one of `a3cqp evaluate`'s two
worker processes runs for `--trials 26`: 13 trials x 5 controllers = 65 arms), in this process, and prints per
simulated second the wall time it took and how many arms were parked (their episode over), and from that timeline
an upper bound on what dropping the parked arms from the batch (compacting it) could save, and per controller when
its episodes ended (simulated time) and how much of the wall came after its last one. `--breakdown` also
times MuJoCo's two halves of a step and the C controller and QP (wrapped calls: ~1 % slower), the floor that no
change of the Python glue can go below; it runs the control period in Python (`A3CQP_NATIVE_TICK=0`, the same
numbers bit for bit), since the C period's calls are out of a wrapper's reach. docs/panda.md, sections "The same
numbers across workers and threads, and where the evaluation's time goes" and "An exact contact pre-filter, the evaluation's floor, ...", have the numbers.
"""
from __future__ import annotations

import argparse
import collections
import functools
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # this checkout's a3cqp_rl/envs/algorithms

import envs.panda as panda_env  # noqa: E402
from a3cqp_rl.config import load_config  # noqa: E402
from envs import panda_eval  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--trials", type=int, default=13)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--hole-segments", type=int, default=None, help="boxes around the bore (config: 32)")
    ap.add_argument("--controllers", default=",".join(panda_eval.CONTROLLERS))
    ap.add_argument("--config", default=str(ROOT / "configs" / "panda_peg_in_hole.yaml"))
    ap.add_argument("--breakdown", action="store_true", help="also time MuJoCo and the C controller and QP")
    args = ap.parse_args()
    if args.breakdown:  # the C period calls MuJoCo and the controller from C, where no Python wrapper sees them
        os.environ["A3CQP_NATIVE_TICK"] = "0"
    spent = _time_native_calls() if args.breakdown else None
    torch.set_num_threads(1)  # as each of evaluate's worker processes
    cfg = load_config(args.config)
    if args.hole_segments is not None:
        cfg.panda.peg_in_hole.hole_segments = args.hole_segments
    rows: list[tuple[float, float, int, int]] = []  # simulated time [s], wall [s], parked arms, arms
    step, last = panda_env.PandaEnv._step, {"wall": None, "steps": 0}

    def timed_step(env, td):  # noqa: ANN001, ANN202
        out = step(env, td)
        last["steps"] += 1
        if last["steps"] % round(1.0 / env.adapt.dt) == 0:  # one simulated second
            now = time.perf_counter()
            if last["wall"] is not None:
                rows.append((float(env.t.max()), now - last["wall"], int(env.parked.sum()), env.num_envs))
            last["wall"] = now
        return out

    panda_env.PandaEnv._step = timed_step
    park, ended = panda_env.PandaEnv.park, {}  # arm -> simulated time its episode ended (its first park)

    def recorded_park(env, idx):  # noqa: ANN001, ANN202
        for i in np.asarray(idx, dtype=np.intp).reshape(-1):
            ended.setdefault(int(i), float(env.t[i]))
        return park(env, idx)

    panda_env.PandaEnv.park = recorded_park
    controllers = tuple(c for c in args.controllers.split(",") if c)
    t0 = time.perf_counter()
    panda_eval._run("peg_in_hole", cfg.panda.policy, panda_eval.trial_seeds(args.seed, args.trials), cfg,
                    controllers, (), 1, False, None, True)
    wall = time.perf_counter() - t0
    print(f"{len(controllers)} controllers x {args.trials} trials, seed {args.seed}, hole segments "
          f"{cfg.panda.peg_in_hole.hole_segments}: {wall:.1f} s wall (start-up included)")
    print("simulated [s] | wall per simulated s [s] | parked arms")
    for t, w, p, _ in rows:
        print(f"{t:13.1f} | {w:24.3f} | {p:11d}")
    r = np.array(rows)
    # A parked arm (no collisions, holding still) costs at most what an arm in free motion costs: its MuJoCo
    # dynamics, sensing and controller. The first simulated seconds, before any contact, give that cost per arm
    # with the period's fixed overhead counted in (an upper bound).
    free = r[r[:, 0] <= 3.0]
    per_arm = float(np.median(free[:, 1] / free[:, 3]))
    bound = float((r[:, 2] * per_arm).sum() / r[:, 1].sum())
    print(f"free motion: {per_arm * 1e3:.1f} ms wall per arm and simulated second (fixed overhead included)")
    print(f"parked arm-seconds {r[:, 2].sum():.0f} of {r[:, 3].sum():.0f}: at most {100 * bound:.1f} % of the "
          "timed wall, the most that compacting the batch (dropping parked arms) could save")
    # the batch's arms are controller-major (panda_eval._run): arm j * trials + k is controller j on trial k
    print("controller | episodes ended at [s simulated]: first, median, last | wall after its last [s]")
    for j, name in enumerate(controllers):
        t_end = np.array([ended.get(j * args.trials + k, np.nan) for k in range(args.trials)])
        after = float(r[r[:, 0] > np.nanmax(t_end), 1].sum())
        print(f"{name:10s} | {np.nanmin(t_end):6.2f} {np.nanmedian(t_end):6.2f} {np.nanmax(t_end):6.2f} | "
              f"{after:5.1f} ({100 * after / r[:, 1].sum():.0f} % of the timed wall)")
    if spent is not None:
        for name, seconds in spent.items():
            print(f"{name:36s} {seconds:6.1f} s  {100 * seconds / wall:4.1f} %")
        floor = sum(spent.values())
        print(f"{'together':36s} {floor:6.1f} s  {100 * floor / wall:4.1f} %  (the rest, {wall - floor:.1f} s: the "
              "numpy/torch glue, the policy, the scene and start-up)")


def _time_native_calls() -> dict[str, float]:
    """Wrap MuJoCo's mj_step1 / mj_step2 and the C controller's assembly, QP and torque law with wall-clock
    counters; returns the dict they add their seconds to."""
    import mujoco

    from a3cqp_rl.control.native import NativeStep
    from a3cqp_rl.qp import solver

    spent: dict[str, float] = collections.defaultdict(float)

    def wrap(owner, attr: str, label: str) -> None:  # noqa: ANN001
        f = getattr(owner, attr)

        @functools.wraps(f)
        def timed(*a, **k):  # noqa: ANN002, ANN003, ANN202
            t = time.perf_counter()
            try:
                return f(*a, **k)
            finally:
                spent[label] += time.perf_counter() - t

        setattr(owner, attr, timed)

    wrap(mujoco, "mj_step1", "MuJoCo mj_step1 (collision in it)")
    wrap(mujoco, "mj_step2", "MuJoCo mj_step2 (constraint solver)")
    wrap(NativeStep, "assemble", "C controller: QP assembly")
    wrap(solver, "_fast_c", "C QP solver")
    wrap(NativeStep, "torque", "C controller: torque law")
    return spent


if __name__ == "__main__":
    main()
