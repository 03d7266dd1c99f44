"""The peg-in-hole evaluation with another stiffness across the tool axis after the first contact: VIC's (its
hand-tuned schedule doubles Table I's k_p on local x and y) or the learned arms' (1: Table I's).

    python docs/experiments/contact_stiffness.py --vic-lateral 1.0 -- --seeds 800-809 --controllers vic \\
        --set panda.ik_rules_scripted=true --json runs/vic_lateral_1.json
    python docs/experiments/contact_stiffness.py --learned-lateral 2.0 -- --seeds 800-809 --controllers learned \\
        --set panda.ik_rules_scripted=true

Everything after `--` goes to `a3cqp evaluate --scene peg_in_hole`. The scales are module constants of
envs/panda_eval.py, so the evaluation runs in this process (`--workers 1`: worker processes would import the module
afresh). docs/panda.md, "Where VIC's like-for-like lead comes from", has the numbers.
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # this checkout's a3cqp_rl/envs/algorithms

import envs.panda_eval as panda_eval  # noqa: E402
from envs.panda_eval import main  # noqa: E402


def _with_learned_lateral(scale: float):  # noqa: ANN202
    """`_scripted` whose stiffness scales also give the learned arms `scale` on local x, y once they have touched."""
    scripted_step = panda_eval._scripted

    def step(env, controllers, trials, latched, since, contact_force):  # noqa: ANN001, ANN202
        W, f_d, stiffness, scripted = scripted_step(env, controllers, trials, latched, since, contact_force)
        learned = ~scripted
        stiffness[learned, :2] = np.where(latched[learned, None], scale, 1.0)
        return W, f_d, stiffness, scripted

    return step


def run(argv: list[str] | None = None) -> int:
    """Parse this script's scales, set them, and run the evaluation with the rest of the arguments."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--vic-lateral", type=float, default=None, help="VIC's k_p scale on local x, y in contact (2)")
    p.add_argument("--learned-lateral", type=float, default=None, help="the learned arms' scale there (1)")
    p.add_argument("rest", nargs="*", help="a3cqp evaluate's arguments, after --")
    args = p.parse_args(argv)
    for flag, value in (("--vic-lateral", args.vic_lateral), ("--learned-lateral", args.learned_lateral)):
        if value is not None and not value > 0:
            p.error(f"{flag} must be > 0, got {value}")
    if args.vic_lateral is not None:
        panda_eval.VIC_CONTACT = (args.vic_lateral, args.vic_lateral, *panda_eval.VIC_CONTACT[2:])
    if args.learned_lateral is not None:
        panda_eval._scripted = _with_learned_lateral(args.learned_lateral)
    return main(["--scene", "peg_in_hole", *args.rest, "--workers", "1"])


if __name__ == "__main__":
    sys.exit(run())
