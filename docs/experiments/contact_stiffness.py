"""The peg-in-hole evaluation with the learned arms given a stiffness across the tool axis after their first contact,
as the variable-impedance baseline's schedule gives its arms (`panda.vic_contact_scale`, whose x and y are 2).

    python docs/experiments/contact_stiffness.py --learned-lateral 2.0 -- --seeds 800-809 --controllers learned \
        --set panda.ik_rules_scripted=true

Everything after `--` goes to `a3cqp evaluate --scene peg_in_hole`. The learned arms' stiffness scales are set in
envs/panda_eval.py's step, so the evaluation runs in this process (`--workers 1`: worker processes would import the
module afresh). VIC's own schedule is a config value (`--set panda.vic_contact_scale=[1,1,0.3333333333333333,1,1,1]`
gives it Table I's stiffness across the tool axis). docs/panda.md, "Where VIC's like-for-like lead comes from", has
the numbers.
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
    """Parse the learned arms' scale, set it, and run the evaluation with the rest of the arguments."""
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--learned-lateral", type=float, required=True,
                   help="the learned arms' k_p scale on local x, y from their first contact on (without it: 1)")
    p.add_argument("rest", nargs="*", help="a3cqp evaluate's arguments, after --")
    args = p.parse_args(argv)
    if not args.learned_lateral > 0:
        p.error(f"--learned-lateral must be > 0, got {args.learned_lateral}")
    panda_eval._scripted = _with_learned_lateral(args.learned_lateral)
    return main(["--scene", "peg_in_hole", *args.rest, "--workers", "1"])


if __name__ == "__main__":
    sys.exit(run())
