"""Benchmark: PandaEnv agent steps per second and aggregate real-time factor for N = 1, 8, 32 arms, with the
peg-in-hole scene's contacts on.

Every arm runs the peg-in-hole procedure with the scripted IK + force-control weights until its peg is on the block
(the insertion phase: peg on the rim or in the bore), then the timed agent steps start (each = 10 control periods of
controller + MuJoCo + sensing + operator/scene at 100 Hz). Reported per N (medians over repeats):
  steps/s    batched env.step() calls per second (TorchRL EnvBase.step, tensordict in and out), physics in one thread
  RTF        aggregate real-time factor N · 10 ms · steps/s
  contacts   mean MuJoCo contacts per arm in the timed window
  2 threads  RTF of the same env with its arms in 2 MuJoCo models stepped in 2 threads (ShardedPandaSim), N >= 8;
             `x 2 thr` = its RTF / RTF (the one-thread env is its peer)
  no filter  RTF of the same env without the exact contact pre-filter (`panda.contact_prefilter: false`: every
             tool-box pair MuJoCo's broad phase passes goes to its narrow phase), N >= 8; `x filter` = RTF / its RTF
  py period  RTF of the same env with its control period in Python (`tick.numpy_tick()`, as `A3CQP_NATIVE_TICK=0`:
             the same C pieces called one by one, envs/native/tick.py); `x tick` = RTF / its RTF
  numpy sns  RTF of that Python period with the sensing in numpy (`sense.numpy_sensing()`, as `A3CQP_NATIVE_SENSE=0`:
             PandaSim's read-out after mj_step1 and f_ext = J^T+ tau_ext, a3cqp_rl/robot/sense.py); `x sense` = the
             Python period's RTF / its RTF
  bare RTF   the same arms, the same number of control periods, run as the bare loop of bench/controller.py (PandaSim
             + A3CQPController, free motion, no env): `env cost` = bare RTF / RTF
Then what a finished (parked) arm costs per control period while its batch runs on, against a live arm in free
motion (PandaEnv(65) with 52 arms parked, and unparked, each against PandaEnv(13); `a3cqp evaluate` parks finished
arms: the controller leaves them out, MuJoCo lets them sleep).
Target: RTF >= 10x at N = 32 on this machine (2 cores).  `--eval POLICY` also times `a3cqp evaluate --scene
peg_in_hole` on 26 trials (learned policy alone, and all five controllers with `--eval-all`) in 1 process and in 2
worker processes (`--workers 2`), finished arms parked in both (target: under a minute).

    python bench/panda_env.py [--quick] [--sizes 1 8 32] [--repeats R] [--eval POLICY [--eval-all]]
"""

from __future__ import annotations

import argparse
import dataclasses
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

from a3cqp_rl.cli import help_summary
from a3cqp_rl.config import ExperimentConfig
from a3cqp_rl.control import A3CQPController
from a3cqp_rl.control.controller import SUBSET_MIN_IDLE
from a3cqp_rl.robot import PandaSim, sense
from envs.native import tick
from envs.panda import PandaEnv


def _scripted(env: PandaEnv) -> None:
    """IK everywhere, force control on the tool axis once the peg touches (the ik_fc baseline's weights)."""
    n = env.num_envs
    W = np.zeros((n, 6, 3))
    W[..., 0] = 1.0
    f_d = np.zeros((n, 6))
    touching = np.linalg.norm(env.f_env[:, :3], axis=1) > 1.0
    W[touching, 2] = [0.0, 0.0, 1.0]
    f_d[touching, 2] = 10.0
    env.hold_weights(np.ones(n, dtype=bool), W, f_d)


def run_env(n: int, steps: int, threads: int = 1, prefilter: bool = True) -> dict[str, float]:
    """Agent steps/s of PandaEnv(n) in the insertion phase and the mean number of contacts per arm."""
    cfg = ExperimentConfig()
    cfg = dataclasses.replace(cfg, panda=dataclasses.replace(cfg.panda, contact_prefilter=prefilter))
    env = PandaEnv(n, cfg, seed=0, sim_threads=threads)
    td = env.reset()
    action = torch.zeros(n, 6, 4)
    guard = 0
    # every peg has touched the block (its first contact, > 1 N): the timed steps are the insertion, in contact
    while not np.isfinite(env.scene.contact_time[:, 0]).all():
        _scripted(env)
        td["action"] = action
        td = env.step(td)["next"]
        guard += 1
        if guard > 1000:
            raise RuntimeError("the arms did not reach the block")
    contacts = []
    t0 = time.perf_counter()
    for _ in range(steps):
        _scripted(env)
        td["action"] = action
        td = env.step(td)["next"]
        contacts.append(env.sim.ncon / n)
    wall = time.perf_counter() - t0
    return {"steps_s": steps / wall, "rtf": n * env.adapt.dt * steps / wall, "contacts": float(np.mean(contacts))}


def run_parked(n: int, parked: int, steps: int) -> float:
    """Wall time per control period [s] of PandaEnv(n) in free motion (the procedure's first agent steps, random
    actions) with its last `parked` arms parked (PandaEnv.park, as `a3cqp evaluate` parks finished arms)."""
    env = PandaEnv(n, ExperimentConfig(), seed=0)
    td = env.reset()
    env.park(np.arange(n - parked, n))
    torch.manual_seed(0)
    for _ in range(5):
        td = env.step(env.rand_action(td))["next"]
    t0 = time.perf_counter()
    for _ in range(steps):
        td = env.step(env.rand_action(td))["next"]
    return (time.perf_counter() - t0) / (steps * env.substeps)


def parked_cost(n: int, parked: int, steps: int, repeats: int) -> tuple[float, float]:
    """(a parked arm's, a live arm's) extra wall time per control period [s]: PandaEnv(n) with `parked` of its arms
    parked and with none, against PandaEnv(n − parked), medians of interleaved runs."""
    few, some, none = [], [], []
    for _ in range(repeats):
        few.append(run_parked(n - parked, 0, steps))
        some.append(run_parked(n, parked, steps))
        none.append(run_parked(n, 0, steps))
    base = statistics.median(few)
    return (statistics.median(some) - base) / parked, (statistics.median(none) - base) / parked


def run_bare(n: int, periods: int) -> float:
    """Aggregate RTF of the bare PandaSim + A3CQPController loop (free motion), the same n and control periods."""
    sim = PandaSim(n, tool="peg")
    ctrl = A3CQPController(n)
    s = sim.observe()
    pos, rot = s.kin.pos.clone(), s.kin.rot.clone()
    w = torch.zeros(n, 6, 3, dtype=torch.float64)
    w[..., 0] = 1.0
    f_d = torch.zeros(n, 6, dtype=torch.float64)
    t0 = time.perf_counter()
    for _ in range(periods):
        out = ctrl.step(s.q, s.qd, s.mass, s.bias, w, f_d, pos, rot, f_env=s.f_env, kin=s.kin)
        sim.step(out.tau)
        s = sim.observe()
    return n * sim.dt * periods / (time.perf_counter() - t0)


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print one row per N; returns 0."""
    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--quick", action="store_true", help="few steps (smoke test)")
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 8, 32])
    p.add_argument("--repeats", type=int, default=3, help="runs per N; the row shows the median")
    p.add_argument("--eval", default=None, metavar="POLICY", help="also time the 26-trial learned-policy evaluation")
    p.add_argument("--eval-all", action="store_true", help="with --eval: also the 5-controller evaluation")
    args = p.parse_args(sys.argv[1:] if argv is None else argv)
    if min(args.sizes) < 1 or args.repeats < 1:
        p.error(f"--sizes and --repeats must be >= 1, got {args.sizes} and {args.repeats}")
    if args.eval is not None and not Path(args.eval).exists():  # found now, not after the benchmark
        p.error(f"--eval {args.eval}: no such policy file or run folder")
    if args.eval_all and args.eval is None:
        p.error("--eval-all needs --eval POLICY")
    torch.set_num_threads(1)
    steps = 20 if args.quick else 200
    repeats = 1 if args.quick else args.repeats
    print(f"PandaEnv benchmark (peg-in-hole, contacts on): {steps} timed agent steps (x10 control periods), "
          f"median of {repeats}")
    print(f"{'N':>4} {'steps/s':>9} {'RTF':>8} {'contacts/arm':>13} {'2 threads':>10} {'x 2 thr':>8} "
          f"{'no filter':>10} {'x filter':>9} {'py period':>10} {'x tick':>7} {'numpy sns':>10} {'x sense':>8} "
          f"{'bare RTF':>9} {'env cost':>9} "
          f"{'target':>18}")
    for n in args.sizes:
        one, two, unfiltered, python_rtf, numpy_rtf = [], [], [], [], []
        for _ in range(repeats):  # interleaved, so that all see the same load
            one.append(run_env(n, steps, threads=1))
            with tick.numpy_tick():
                python_rtf.append(run_env(n, steps, threads=1)["rtf"])
            with sense.numpy_sensing():  # (no C read-out: the Python period)
                numpy_rtf.append(run_env(n, steps, threads=1)["rtf"])
            if n >= 8:
                two.append(run_env(n, steps, threads=2)["rtf"])
                unfiltered.append(run_env(n, steps, prefilter=False)["rtf"])
        r = sorted(one, key=lambda x: x["rtf"])[len(one) // 2]
        rtf2 = (f"{statistics.median(two):>9.2f}x {statistics.median(two) / r['rtf']:>7.2f}x" if two
                else f"{'-':>10} {'-':>8}")
        plain = statistics.median(unfiltered) if unfiltered else None  # the peer: MuJoCo's own pairs
        nofilter = f"{plain:>9.2f}x {r['rtf'] / plain:>8.2f}x" if plain else f"{'-':>10} {'-':>9}"
        py, slow = statistics.median(python_rtf), statistics.median(numpy_rtf)
        sensing = f"{py:>9.2f}x {r['rtf'] / py:>6.2f}x {slow:>9.2f}x {py / slow:>7.2f}x"
        bare = statistics.median(run_bare(n, steps * 10) for _ in range(repeats))
        target = f">=10x RT: {'met' if r['rtf'] >= 10 else 'NOT met'}" if n == 32 else "-"
        print(f"{n:>4} {r['steps_s']:>9.1f} {r['rtf']:>7.2f}x {r['contacts']:>13.1f} {rtf2} {nofilter} {sensing} "
              f"{bare:>8.2f}x {bare / r['rtf']:>8.2f}x {target:>18}")
    # quick: enough parked arms that the controller leaves them out (below SUBSET_MIN_IDLE it computes and holds them)
    n_all, n_parked = (SUBSET_MIN_IDLE + 12, SUBSET_MIN_IDLE + 4) if args.quick else (65, 52)
    per_parked, per_live = parked_cost(n_all, n_parked, steps, repeats)
    # a parked arm's cost is a difference of two timings: below the noise it can come out at zero or negative
    ratio = (f"x{per_live / per_parked:.1f}" if per_parked > 0.02 * per_live else
             f"a parked arm's cost is below this run's timing noise (under 2 % of a live arm's)")
    print(f"finished arms (PandaEnv({n_all}), {n_parked} parked, free motion): {1e6 * per_parked:.1f} us per parked "
          f"arm and control period, {1e6 * per_live:.1f} us per live arm (peer, the same env unparked): {ratio}")
    if args.eval:
        from envs.panda_eval import CONTROLLERS, evaluate

        for label, controllers in [("learned policy", ("learned",))] + ([("5 controllers", CONTROLLERS)]
                                                                         if args.eval_all else []):
            walls = {}
            for workers in (2, 1):  # finished arms parked (evaluate's default) in both
                t0 = time.perf_counter()
                res = evaluate("peg_in_hole", args.eval, 26, 0, controllers=controllers, progress=False,
                               workers=workers)
                walls[workers] = time.perf_counter() - t0
            print(f"26-trial evaluation, {label}: {walls[1]:.1f} s in 1 process ({res.sim_seconds:.0f} s simulated); "
                  f"{walls[2]:.1f} s in 2 worker processes (--workers 2), x{walls[1] / walls[2]:.2f}; target < 60 s: "
                  f"{'met' if min(walls.values()) < 60 else 'NOT met'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
