"""Single 1 ms losses of a pressed contact on peg-in-hole: how often each controller's |f_env| drops below 0.5 N
between two samples above 10 N.

    python docs/experiments/contact_dropouts.py [--seed 0] [--trials 13] [--controllers learned,ik_fc,ik]
        [--solref 0.01] [--impratio 1] [--friction 0.001] [--margin-gap 0.001]

Runs `envs.panda_eval.evaluate` (one batch, `workers=1`: every controller on the same trials) with the f_env of every
1 kHz control period recorded, and prints per controller the pressing samples, the dropouts among them and the largest
|f_env|. The options change the block's contact in the live MuJoCo model (the scene's geoms: contype 1, conaffinity 2)
before the run: `--solref` its time constant [s] (default 5 ms), `--impratio` MuJoCo's option, `--friction` its
sliding friction, `--margin-gap` both margin and gap [m] (contacts found that far out, force only in penetration).
docs/panda.md, section "Joint limits under random weights, contact dropouts, and the runs that yield", has the numbers.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's a3cqp_rl/envs/algorithms

import numpy as np

import envs.panda as panda
from a3cqp_rl.config import load_config
from envs.panda_eval import evaluate


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--trials", type=int, default=13)
    ap.add_argument("--controllers", default="learned,ik_fc,ik")
    ap.add_argument("--solref", type=float, default=None, help="the block's contact time constant [s]")
    ap.add_argument("--impratio", type=float, default=None)
    ap.add_argument("--friction", type=float, default=None, help="the block's sliding friction")
    ap.add_argument("--margin-gap", type=float, default=None, help="margin = gap of the block's geoms [m]")
    args = ap.parse_args()
    samples: list[np.ndarray] = []
    tick, init = panda.PandaEnv._tick, panda.PandaEnv.__init__

    def recording_tick(self, k, *a, **kw):  # noqa: ANN001, ANN202
        out = tick(self, k, *a, **kw)
        samples.append(np.linalg.norm(self.f_env[:, :3], axis=1))
        return out

    def init_with_contact(self, *a, **kw) -> None:  # noqa: ANN001
        init(self, *a, **kw)
        for m in self.sim.models:
            block = (m.geom_contype == 1) & (m.geom_conaffinity == 2)
            if args.solref is not None:
                m.geom_solref[block, 0] = args.solref
            if args.friction is not None:
                m.geom_friction[block, 0] = args.friction
            if args.margin_gap is not None:
                m.geom_margin[block] = args.margin_gap
                m.geom_gap[block] = args.margin_gap
            if args.impratio is not None:
                m.opt.impratio = args.impratio

    panda.PandaEnv._tick, panda.PandaEnv.__init__ = recording_tick, init_with_contact
    controllers = tuple(args.controllers.split(","))
    evaluate("peg_in_hole", None, args.trials, seed=args.seed, config=load_config("configs/panda_peg_in_hole.yaml"),
             controllers=controllers, progress=False, workers=1)
    f = np.array(samples)  # [periods, arms]: the controllers' arms in the order given, `trials` each
    print(f"seed {args.seed}, {args.trials} trials per controller, one batch")
    print(f"{'controller':<12} {'pressing (> 10 N)':>18} {'dropouts (< 0.5 N)':>20} {'largest |f_env|':>16}")
    for c, name in enumerate(controllers):
        g = f[:, c * args.trials:(c + 1) * args.trials]
        pressing = g > 10.0
        drop = (g[1:-1] < 0.5) & pressing[:-2] & pressing[2:]
        n = int(pressing.sum())
        print(f"{name:<12} {n:>18,} {int(drop.sum()):>11,} ({100 * drop.sum() / max(n, 1):4.1f} %) {g.max():>13.0f} N")


if __name__ == "__main__":
    main()
