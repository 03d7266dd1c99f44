"""What eq. 30's cost of the desired force (α4) makes a point-mass policy do in contact and in the Panda's checks.

    python docs/experiments/reward_fd_cost.py --alpha4 0 1 2 --seeds 0-7 [--out /tmp/fd_cost]

For each α4, trains `configs/point_mass_a2c_fig5_fd_1e6.yaml` (the Panda configs' policy: 1e6 steps on the C
iteration, α = (0.5, 20, 4, α4)) on every seed (`a3cqp train --seeds`), then prints per run the two transfer checks
of `a3cqp evaluate --scene` (free motion: mean ẇ1 > 0; under the operator's push: mean ẇ2 > 0 and ḟd < 0) and the
weights (w1, w2, w3) and f_d [N] the policy holds after 3 s on a fixed contact observation of the peg
(|e| = 25 mm, |f_env| = 15 N, no operator; eq. 29 integrated from IK with Table II's rates and the peg's f̄_d = 10 N).
docs/panda.md, section "Why IK only passes the wrist's limit on the peg", has the numbers.
"""
from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import yaml

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))  # this checkout's a3cqp_rl/envs/algorithms

from a3cqp_rl.adaptation import integrate_force, integrate_weights
from a3cqp_rl.config import load_config
from algorithms.a2c import load_policy
from algorithms.train import parse_seeds
from envs.panda_eval import free_motion_rates, guided_rates

BASE = ROOT / "configs" / "point_mass_a2c_fig5_fd_1e6.yaml"


PEG_ADAPTATION = load_config(ROOT / "configs" / "panda_peg_in_hole.yaml").adaptation
"""Table II's rates with the peg's f̄_d = 10 N."""


def held_contact(policy, e: float, f_env: float) -> tuple[np.ndarray, float]:  # noqa: ANN001
    """Weights [3] and f_d [N] after 3 s of eq. 29 on the fixed observation (e [m], f_env [N], no operator)."""
    a = PEG_ADAPTATION
    half = 0.5 * a.sigma_w
    logits, f_d = torch.tensor([[half, -half, -half]], dtype=torch.float64), torch.zeros(1, dtype=torch.float64)
    obs = torch.tensor([[e / a.e_max, f_env / a.f_env_max, 0.0]], dtype=torch.float32)
    with torch.no_grad():
        for _ in range(round(3.0 / a.dt)):
            rates = policy(obs).double()
            logits, w = integrate_weights(logits, rates[:, :3], a.sigma_w, a.dt, check=False)
            f_d = integrate_force(f_d, rates[:, 3], a.sigma_f, a.dt, a.f_d_max, check=False)
    return w[0].numpy(), float(f_d[0])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--alpha4", type=float, nargs="+", default=[0.0, 1.0, 2.0])
    ap.add_argument("--seeds", type=parse_seeds, default=list(range(8)), help="e.g. 0-7")
    ap.add_argument("--out", type=Path, default=Path(tempfile.gettempdir()) / "fd_cost")
    args = ap.parse_args()
    base = yaml.safe_load(BASE.read_text())
    seeds = ",".join(map(str, args.seeds))
    for a4 in args.alpha4:
        cfg = dict(base, reward=dict(base["reward"], alpha=[*base["reward"]["alpha"][:3], a4]))
        out = args.out / f"alpha4_{a4:g}"
        out.mkdir(parents=True, exist_ok=True)
        (out / "config.yaml").write_text(yaml.safe_dump(cfg))
        subprocess.run([sys.executable, "-m", "a3cqp_rl.cli", "train", "--config", str(out / "config.yaml"),
                        "--seeds", seeds, "--out", str(out), "--no-plots", "--no-eval", "--quiet", "--force"],
                       cwd=ROOT, check=True, stdout=subprocess.DEVNULL)
        passed = 0
        for s in args.seeds:
            policy = load_policy(out / f"seed_{s}" / "policy.pt")
            free, guided = free_motion_rates(policy), guided_rates(policy)
            ok = free[0] > 0 and guided[1] > 0 and guided[3] < 0
            passed += ok
            w, f_d = held_contact(policy, 0.025, 15.0)
            print(f"α4 = {a4:g}, seed {s}: checks {'pass' if ok else 'fail'} (free ẇ1 {free[0]:+.2f}; pushed ẇ2 "
                  f"{guided[1]:+.2f}, ḟd {guided[3]:+.2f}); in contact w = {np.round(w, 2)}, f_d = {f_d:.1f} N")
        print(f"α4 = {a4:g}: {passed} of {len(args.seeds)} runs pass both checks")


if __name__ == "__main__":
    main()
