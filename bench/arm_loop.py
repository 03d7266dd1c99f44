"""The closed loop the controller benchmarks time (bench/controller.py, bench/hierarchy.py): N simulated Pandas at
1 kHz, random softmax task weights and desired forces switching every 50 ms, a fixed random Cartesian target, no
contact; named parts of the controller's step timed by wrapping its methods."""

from __future__ import annotations

import time
from typing import Any, Callable

import torch


class PartTimer:
    """Accumulates the time spent in wrapped methods under part names (reset before each step)."""

    def __init__(self, clock: Callable[[], float] = time.perf_counter) -> None:
        self.clock = clock
        self.parts: dict[str, float] = {}

    def wrap(self, obj: Any, attr: str, part: str) -> None:
        """Replace `obj.attr` by a wrapper adding its run time [s] to `part`."""
        fn, self.parts[part] = getattr(obj, attr), 0.0

        def wrapper(*a, **kw):  # noqa: ANN002, ANN003, ANN202
            t = self.clock()
            out = fn(*a, **kw)
            self.parts[part] += self.clock() - t
            return out

        setattr(obj, attr, wrapper)

    def reset(self) -> None:
        """Zero every part."""
        for k in self.parts:
            self.parts[k] = 0.0


def drive(ctrl, sim, steps: int, warmup: int, timer: PartTimer, record: Callable[[float, float], None],  # noqa: ANN001
          seed: int = 0) -> None:
    """Run `warmup + steps` control periods of `ctrl` on `sim`; after the warm-up, `record(ctrl_s, sim_s)` each step
    with the step's controller and MuJoCo times [s] (`timer.parts` then holds that step's parts)."""
    gen = torch.Generator().manual_seed(seed)
    n, clock = sim.n, timer.clock
    s = sim.observe()
    pos0, rot0 = ctrl.model.fk(s.q.clone())
    pos_d = pos0 + 0.2 * (torch.rand(n, 3, generator=gen, dtype=torch.float64) - 0.5)
    for k in range(warmup + steps):
        if k % 50 == 0:
            w = torch.softmax(6.0 * (torch.rand(n, 6, 3, generator=gen, dtype=torch.float64) - 0.5), -1)
            f_d = 10.0 * torch.rand(n, 6, generator=gen, dtype=torch.float64)
        timer.reset()
        t0 = clock()
        out = ctrl.step(s.q, s.qd, s.mass, s.bias, w, f_d, pos_d, rot0, f_env=s.f_env, kin=s.kin)
        t1 = clock()
        sim.step(out.tau)
        s = sim.observe()
        if k >= warmup:
            record(t1 - t0, clock() - t1)
