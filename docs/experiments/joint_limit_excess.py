"""How far a joint goes past its datasheet limit under random held actions (the slow test's loop), per seed.

    python docs/experiments/joint_limit_excess.py --seeds 1-6 [--steps 3000] [--q-margin 0.05] [--include-f-ext]
                                                  [--end-stop-tc 0.02] [--stop-share 1.0] [--scene guidance]

Runs `envs.panda_eval.limit_stress` as the slow test
`tests/test_panda_env.py::test_joint_and_torque_limits_hold_over_many_random_episodes` does: 8 arms on peg-in-hole
(3-s trials, the operator on), random actions held for 20 agent steps, done arms reset. Prints per seed the worst
excess past a datasheet position limit [mrad] (negative: the closest approach, inside), its joint and arm, the
largest |τ|/τ_max and the QP fallbacks (1 kHz periods of one arm that braked because the QP failed). `--q-margin` sets
ControllerOptions.q_margin (default 0.01 rad), `--include-f-ext` ControllerOptions.joint_limits_include_f_ext,
`--end-stop-tc` the time constant [s] of the joints' end stops (panda.xml: 0.002; MuJoCo's default, before
2026-11-28: 0.02), `--stop-share` ControllerOptions.viability_stop_share (default 0.9; 1.0 before 2026-12-01),
`--scene` the scene (default peg_in_hole; guidance: no contact, the operator guides). docs/panda.md, sections
"Joint limits under random weights, contact dropouts, and the runs that yield", "Stiff end stops, ..." and "Headroom
in the joint-limit bound, ..." have the numbers.
"""
from __future__ import annotations

import argparse
import logging
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))  # this checkout's a3cqp_rl/envs/algorithms

from a3cqp_rl.config import config_from_dict
from a3cqp_rl.control import ControllerOptions
from algorithms.train import parse_seeds
from envs.panda import PandaEnv
from envs.panda_eval import limit_stress

ARMS = 8
# the test's shortened procedure (tests/test_panda_env.py, FAST_PEG) with 3-s trials
CONFIG = {"panda": {"peg_in_hole": {"settle_time": 0.1, "approach_time": 1.0, "align_time": 3.0, "time_limit": 3.0}}}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--seeds", type=parse_seeds, default=[1, 2, 3], help="e.g. 1-6 or 1,3,5")
    ap.add_argument("--steps", type=int, default=3000, help="agent steps (10 ms each) per seed")
    ap.add_argument("--q-margin", type=float, default=ControllerOptions.q_margin)
    ap.add_argument("--include-f-ext", action="store_true")
    ap.add_argument("--end-stop-tc", type=float, default=None, help="end-stop time constant [s] (default: panda.xml's)")
    ap.add_argument("--stop-share", type=float, default=ControllerOptions.viability_stop_share)
    ap.add_argument("--scene", choices=["peg_in_hole", "guidance"], default="peg_in_hole")
    args = ap.parse_args()
    if args.end_stop_tc is not None:
        _set_end_stops(args.end_stop_tc)
    logging.getLogger("a3cqp_rl.control.controller").setLevel(logging.ERROR)  # one warning per fallback otherwise
    options = ControllerOptions(q_margin=args.q_margin, joint_limits_include_f_ext=args.include_f_ext,
                                viability_stop_share=args.stop_share)
    print(f"{ARMS} arms x {args.steps} agent steps, {args.scene}, q_margin {args.q_margin} rad, include_f_ext "
          f"{args.include_f_ext}, stop_share {args.stop_share}")
    config = config_from_dict({"panda": {**CONFIG["panda"], "scene": args.scene}})
    for seed in args.seeds:
        r = limit_stress(ARMS, args.steps, seed, config, options)
        print(f"seed {seed}: worst excess {1e3 * r.worst_excess:+6.2f} mrad (< 0: inside; joint {r.joint}, "
              f"arm {r.arm}), "
              f"max |tau|/tau_max {r.worst_torque_ratio:.3f}, max |dq|/dq_max {r.worst_speed_ratio:.2f}, "
              f"QP fallback periods {r.fallbacks}")


def _set_end_stops(timeconst: float) -> None:
    """Every PandaEnv built from here on gets joint end stops (MuJoCo joint-limit solref) of this time constant [s]."""
    build = PandaEnv.__init__

    def init(self, *a, **k) -> None:  # noqa: ANN001, ANN002, ANN003
        build(self, *a, **k)
        for m in self.sim.models:
            m.jnt_solref[:, 0] = timeconst

    PandaEnv.__init__ = init


if __name__ == "__main__":
    main()
