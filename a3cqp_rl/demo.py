"""`a3cqp demo ...`: demos. `a3cqp demo controller` runs the Panda A3CQP controller through the four tasks."""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path

import numpy as np
import torch

from a3cqp_rl.cli import error_exit, help_summary
from a3cqp_rl.run_folder import RunFolderError, check_output_path

__all__ = ["main", "controller_demo"]


def _phase_logits(t: float) -> tuple[np.ndarray, float, np.ndarray, str]:
    """Scripted schedule: per-axis weight logits [6, 3] (IK, AC, FC), f_d along the tool axis, push, phase name.

    The logits move toward these goals at 10 per second, so each switch takes ~1 s. Goals are ±5 (weights
    0.99991 / 0.00005): with the ±3 of σw = 6 (eq. 29) the inactive tasks keep ~0.25 % weight, enough for IK to
    pull ~20 % of its acceleration on an FC axis (see ControllerOptions.cartesian_regularization).
    """
    ik, ac, fc = np.array([5.0, -5.0, -5.0]), np.array([-5.0, 5.0, -5.0]), np.array([-5.0, -5.0, 5.0])
    push = np.zeros(3)
    if t < 1.2:  # IK: move to the target above the table
        return np.tile(ik, (6, 1)), 0.0, push, "IK"
    if t < 3.5:  # AC: the operator pushes the handle sideways for 0.3 s, then holds it back for 0.3 s
        if 2.2 <= t < 2.5:
            push = np.array([0.0, 10.0, 0.0])
        elif 2.5 <= t < 2.8:
            push = np.array([0.0, -10.0, 0.0])
        return np.tile(ac, (6, 1)), 0.0, push, "AC"
    if t < 4.5:  # IK + JC: back to the target (JC keeps the elbow centred in the null space)
        return np.tile(ik, (6, 1)), 0.0, push, "IK+JC"
    logits = np.tile(ik, (6, 1))  # FC on the tool axis (local z), IK on the others: press on the table
    logits[2] = fc
    return logits, 10.0, push, "FC"


def controller_demo(seconds: float = 6.0, png: Path | None = None, tool: str = "peg") -> Path:
    """Simulate one Panda switching IK -> AC -> IK+JC -> FC with smooth (C⁰) weights; write and return a PNG."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from a3cqp_rl.control import A3CQPController, wrench_from_joint_torques
    from a3cqp_rl.robot import PANDA_HOME, PANDA_LIMITS, PandaModel, PandaSim, table_xml

    model = PandaModel(tool=tool)
    ctrl = A3CQPController(1, model=model)
    q_home = torch.tensor([PANDA_HOME], dtype=torch.float64)
    pos_home, rot_d = model.fk(q_home)
    target = pos_home + torch.tensor([[0.1, 0.0, -0.05]], dtype=torch.float64)
    table_top = float(target[0, 2]) - 0.01  # 1 cm below the IK target
    sim = PandaSim(1, tool=tool, scene=table_xml(height=table_top, center=(float(target[0, 0]), 0.0)))
    steps = int(round(seconds / sim.dt))
    logits = torch.tensor(_phase_logits(0.0)[0], dtype=torch.float64)
    rate = 10.0  # logits move at most this much per second, so the weights are C⁰ (eq. 29)
    rec: dict[str, list] = {k: [] for k in ("t", "err", "f_env", "f_op", "wrench", "w_z", "w_x", "gap", "phase")}
    s = sim.observe()
    t0 = time.perf_counter()
    for k in range(steps):
        t = k * sim.dt
        goal, f_d_z, push, phase = _phase_logits(t)
        logits = logits + (torch.tensor(goal) - logits).clamp(-rate * sim.dt, rate * sim.dt)
        weights = torch.softmax(logits, dim=-1).unsqueeze(0)
        f_d = torch.zeros(1, 6, dtype=torch.float64)
        f_d[0, 2] = f_d_z * float(weights[0, 2, 2])  # ramp the desired force with the FC weight
        kin = s.kin  # the tool tip's kinematics from MuJoCo's step (same as model.kinematics(s.q, s.qd) to 1e-8)
        f_ext = wrench_from_joint_torques(s.tau_ext, kin.jac, s.mass)
        out = ctrl.step(s.q, s.qd, s.mass, s.bias, weights, f_d, target, rot_d, f_ext=f_ext, f_env=s.f_env, kin=kin)
        if np.any(push):
            sim.push(push[None], site="handle")
        sim.step(out.tau)
        lim_gap = np.minimum(s.q[0].numpy() - PANDA_LIMITS.q_min, np.array(PANDA_LIMITS.q_max) - s.q[0].numpy())
        rec["t"].append(t)
        rec["err"].append(out.pose_error[0].numpy().copy())
        rec["f_env"].append(s.f_env[0, :3].numpy().copy())
        rec["f_op"].append(push.copy())
        rec["wrench"].append(out.wrench[0, :3].numpy().copy())
        rec["w_z"].append(weights[0, 2].numpy().copy())
        rec["w_x"].append(weights[0, 1].numpy().copy())
        rec["gap"].append(lim_gap.min())
        rec["phase"].append(phase)
        s = sim.observe()
    wall = time.perf_counter() - t0
    r = {k: np.array(v) for k, v in rec.items()}

    fig, ax = plt.subplots(4, 1, figsize=(10, 11), sharex=True)
    ax[0].plot(r["t"], 1e3 * np.linalg.norm(r["err"][:, :3], axis=1), label="position error |e_p| [mm]")
    ax[0].plot(r["t"], 1e3 * np.linalg.norm(r["err"][:, 3:], axis=1), label="orientation error |e_θ| [mrad]")
    ax[0].set_yscale("symlog", linthresh=1.0)
    ax[0].set_ylabel("error")
    ax[1].plot(r["t"], r["f_env"][:, 2], label="contact force on tool, z (F/T) [N]")
    ax[1].plot(r["t"], r["f_op"][:, 1], label="operator push at handle, y [N]")
    ax[1].plot(r["t"], r["wrench"][:, 2], "--", label="QP wrench f*, z [N]")
    ax[1].plot(r["t"], r["wrench"][:, 1], ":", label="QP wrench f*, y [N]")
    ax[1].set_ylabel("force [N]")
    for i, name in enumerate(("w1 IK", "w2 AC", "w3 FC")):
        ax[2].plot(r["t"], r["w_z"][:, i], label=f"{name} (local z)")
        ax[2].plot(r["t"], r["w_x"][:, i], ":", label=f"{name} (local y)")
    ax[2].set_ylabel("weights")
    ax[3].plot(r["t"], r["gap"], label="min distance to a joint limit [rad]")
    ax[3].set_ylabel("rad")
    ax[3].set_xlabel("time [s]")
    changes = [0] + [i for i in range(1, len(r["phase"])) if r["phase"][i] != r["phase"][i - 1]]
    for a in ax:
        for i in changes:
            a.axvline(r["t"][i], color="0.7", lw=0.8)
        a.legend(loc="upper right", fontsize=8)
    for i in changes:
        ax[0].text(r["t"][i] + 0.02, ax[0].get_ylim()[1] * 0.5, r["phase"][i], fontsize=9)
    fig.suptitle(f"A3CQP controller on the Panda ({tool}), {seconds:.1f} s simulated in {wall:.1f} s")
    fig.tight_layout()
    png = png or Path("runs") / "demo_controller.png"
    png.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(png, dpi=110)
    plt.close(fig)
    fc = r["phase"] == "FC"
    if fc.any():
        tail = r["f_env"][fc][-500:, 2]
        print(f"FC phase, last 0.5 s: contact force {tail.mean():.2f} ± {tail.std():.2f} N "
              f"(f_d = 10 N x w3 = {10 * r['w_z'][-1, 2]:.2f} N)")
    ik = r["phase"] == "IK"
    if ik.any():
        print(f"IK phase: final position error {1e3 * np.linalg.norm(r['err'][ik][-1, :3]):.3f} mm")
    print(f"simulated {seconds:.1f} s in {wall:.1f} s ({seconds / wall:.2f}x real time)")
    return png


def main(argv: list[str] | None = None) -> int:
    """Dispatch `a3cqp demo <name>`; returns the exit code."""
    parser = argparse.ArgumentParser(prog="a3cqp demo", description=help_summary(__doc__))
    sub = parser.add_subparsers(dest="name", required=True)
    p = sub.add_parser("controller", help="Panda A3CQP controller: IK -> AC -> IK+JC -> FC, plot to a PNG")
    p.add_argument("--seconds", type=float, default=6.0, help="simulated time [s] (the schedule needs 6)")
    p.add_argument("--out", type=Path, default=None, help="PNG path (default: runs/demo_controller.png)")
    p.add_argument("--tool", default="peg", choices=("peg", "disc", "none"), help="tool below the F/T sensor")
    args = parser.parse_args(sys.argv[1:] if argv is None else argv)
    torch.set_num_threads(max(1, min(2, os.cpu_count() or 1)))
    if args.name == "controller":
        if not args.seconds >= 0.01:  # NaN too
            p.error(f"--seconds must be at least 0.01 (one step of the plotted record), got {args.seconds}")
        try:
            if args.out is not None:
                if not args.out.suffix and not args.out.is_dir():  # matplotlib would add it: say the real name
                    args.out = args.out.with_suffix(".png")
                check_output_path(args.out, "--out")
        except RunFolderError as exc:
            return error_exit(exc)
        path = controller_demo(args.seconds, args.out, args.tool)
        print(f"wrote {path}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
