"""Benchmark: the cost of the per-axis leak's extra rate (`A3CQPController.step(leak_extra=...)`) and of the env that
passes it (`panda.idle_force: damps`).

Reported per N (medians over repeats, this thread's CPU time so that a shared machine's waiting is left out):
  step µs      A3CQPController.step (per_axis leak, default backend) on the same random inputs, leak_extra None and a
               [N, 6] rate; `ratio` = with / without (the peer is measured in the same run, interleaved)
  env µs/tick  PandaEnv (guidance scene) per 1 kHz control period with an idle share on every axis of every arm
               (w = (0, 0.5, 0.5), f_d = 0 held: the controller gets leak_extra each period)

    python bench/leak_extra.py [--quick] [--sizes 1 32] [--repeats 7]   (or `a3cqp bench leak`)
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time

import numpy as np
import torch

from a3cqp_rl.cli import help_summary
from a3cqp_rl.config import config_from_dict
from a3cqp_rl.control import A3CQPController, ControllerOptions
from a3cqp_rl.robot import PandaModel, mujoco_dynamics
from envs.panda import PandaEnv


def _inputs(n: int) -> dict:
    """Controller inputs at random states near the home pose (the same for every call)."""
    gen = torch.Generator().manual_seed(0)
    f64 = torch.float64
    model = PandaModel()
    q = torch.tensor([0.0, -0.785, 0.0, -2.356, 0.0, 1.571, 0.785], dtype=f64) + 0.2 * torch.randn(n, 7, generator=gen,
                                                                                                     dtype=f64)
    qd = 0.3 * torch.randn(n, 7, generator=gen, dtype=f64)
    mass, bias = mujoco_dynamics(model.mj_model, q, qd)
    kin = model.kinematics(q, qd)
    return dict(q=q, qd=qd, mass=mass, bias=bias, kin=kin,
                weights=torch.softmax(2.0 * torch.randn(n, 6, 3, generator=gen, dtype=f64), dim=-1),
                f_d=5.0 * torch.rand(n, 6, generator=gen, dtype=f64), pos_d=kin.pos + 0.02, rot_d=kin.rot)


def step_cost(n: int, repeats: int, calls: int = 300) -> tuple[float, float]:
    """Median CPU µs of one controller step with leak_extra None and with a rate (interleaved)."""
    inputs = _inputs(n)
    ctrl = A3CQPController(n, options=ControllerOptions(leak_axes="per_axis"))
    start = (inputs["q"].clone(), inputs["qd"].clone())
    extra = torch.full((n, 6), 5.0, dtype=torch.float64)
    times: dict[bool, list[float]] = {False: [], True: []}
    for _ in range(repeats):
        for with_extra in (False, True):
            t0 = time.thread_time()
            for _ in range(calls):
                ctrl.reset(*start)
                ctrl.step(**inputs, leak_extra=extra if with_extra else None)
            times[with_extra].append((time.thread_time() - t0) / calls * 1e6)
    return statistics.median(times[False]), statistics.median(times[True])


def env_tick_cost(n: int, repeats: int, agent_steps: int = 20) -> float:
    """Median CPU µs per control period of the guidance env with an idle share on every axis."""
    env = PandaEnv(n, config_from_dict({"panda": {"scene": "guidance", "idle_force": "damps"}}), seed=0)
    env.reset()
    w, f_d = np.tile([0.0, 0.5, 0.5], (n, 6, 1)), np.zeros((n, 6))
    td = env._output(done=np.zeros(n, dtype=bool), terminated=np.zeros(n, dtype=bool))
    held = np.ones(n, dtype=bool)

    def run(k: int) -> float:
        nonlocal td
        t0 = time.thread_time()
        for _ in range(k):
            env.hold_weights(held, w, f_d)
            td["action"] = torch.zeros(n, 6, 4)
            td = env.step(td)["next"]
        return (time.thread_time() - t0) / (k * env.substeps) * 1e6

    run(3)
    return statistics.median(run(agent_steps) for _ in range(repeats))


def main(argv: list[str] | None = None) -> int:
    """Print the table of the module docstring; returns 0."""
    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--quick", action="store_true", help="few calls (smoke test)")
    p.add_argument("--sizes", type=int, nargs="+", default=[1, 32])
    p.add_argument("--repeats", type=int, default=7, help="runs per N; the row shows the median")
    a = p.parse_args(argv)
    torch.set_num_threads(1)
    calls, agent_steps, repeats = (10, 2, 1) if a.quick else (300, 20, a.repeats)
    print(f"{'N':>4} {'step µs (None)':>15} {'step µs (rate)':>15} {'ratio':>6} {'env µs/tick':>12}")
    for n in a.sizes:
        plain, extra = step_cost(n, repeats, calls)
        tick = env_tick_cost(n, repeats, agent_steps)
        print(f"{n:>4} {plain:>15.1f} {extra:>15.1f} {extra / plain:>6.3f} {tick:>12.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
