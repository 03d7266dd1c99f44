"""Whether a scene's key poses lie within the Panda's reach, checked before a trial is simulated.

A hole, a plate or a waypoint moved out of the arm's workspace makes every trial fail at its time limit with nothing
to say why. Each key pose of the scene's procedure (the tool tip at the peg's approach and inserted poses, the
polishing zones, the guidance waypoints; orientation: the tool's at home) is solved by Levenberg-Marquardt inverse
kinematics from home with the joints held inside their limits; a pose the solution ends away from is out of reach.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from a3cqp_rl.config import PandaEnvConfig
from a3cqp_rl.robot import PANDA_HOME, PANDA_LIMITS, PandaModel
from envs.scenarios import SCENES, turn_about_vertical

POSITION_TOLERANCE = 0.002
"""Tool-tip distance [m] from a key pose above which IK's end counts as not reaching it."""
ROTATION_TOLERANCE = 0.02
"""Tool-axis angle [rad] from a key pose above which IK's end counts as not reaching it."""


@dataclass(frozen=True)
class KeyPose:
    """A pose the scene's reference visits: tool-tip position [m] and rotation, the arm's base frame."""

    name: str
    pos: np.ndarray
    rot: np.ndarray
    keys: str
    """The config values that place it."""


def key_poses(pcfg: PandaEnvConfig, home_pos: np.ndarray, home_rot: np.ndarray) -> list[KeyPose]:
    """The procedure's nominal poses of `pcfg.scene` (no trial's misalignment, plate height or zone; the guidance
    waypoints also at the ends of their turn)."""
    if pcfg.scene == "peg_in_hole":
        c = pcfg.peg_in_hole
        hole = np.array([c.hole_center[0], c.hole_center[1], c.hole_top])
        keys = "panda.peg_in_hole.hole_center, hole_top"
        return [KeyPose("the approach pose above the hole", hole + [0.0, 0.0, c.approach_height], home_rot, keys),
                KeyPose("the peg at its success depth", hole - [0.0, 0.0, c.success_depth], home_rot, keys)]
    if pcfg.scene == "polishing":
        c = pcfg.polishing
        zone = np.array(c.plate_center) + np.array(c.start_offset)
        poses = []
        for k, move in enumerate(((0.0, 0.0), *c.relocations)):  # each relocation moves the zone on from the last
            zone = zone + np.array(move)
            what = "the first polishing zone" if k == 0 else f"the polishing zone after relocation {k}"
            for dx, dy in ((1, 0), (0, 1), (-1, 0), (0, -1)):  # the circle's extremes
                xy = zone + c.circle_radius * np.array([dx, dy])
                poses.append(KeyPose(what, np.array([xy[0], xy[1], c.plate_top - c.preload]), home_rot,
                                     "panda.polishing.plate_center, start_offset, relocations, plate_top"))
        return poses
    c = pcfg.guidance
    poses = []
    # a trial's turn moves a waypoint along an arc about the handle's home: its two ends are checked as well (not
    # the ball of `waypoint_spread` about each point: a few cm inside a workspace of ~0.8 m)
    for turn in sorted({0.0, -c.waypoint_turn_deg, c.waypoint_turn_deg}, key=abs):
        for k, w in enumerate(turn_about_vertical(np.array(c.waypoints), np.deg2rad(turn))):
            what = f"waypoint {k + 1}" + (f" turned {turn:+g} deg" if turn else "")
            poses.append(KeyPose(what, home_pos + w, home_rot, "panda.guidance.waypoints, waypoint_turn_deg"))
    return poses


def _pose_error(model: PandaModel, q: torch.Tensor, pos_d: torch.Tensor, rot_d: torch.Tensor):  # noqa: ANN202
    """Kinematics at q and the 6-D error to the goals (m; rad, small-angle form of R -> R_d)."""
    k = model.kinematics(q)
    e_rot = 0.5 * torch.linalg.cross(k.rot, rot_d, dim=1).sum(dim=-1)
    return k, torch.cat([pos_d - k.pos, e_rot], dim=-1)


def ik_miss(model: PandaModel, poses: list[KeyPose], iterations: int = 150) -> tuple[np.ndarray, np.ndarray]:
    """Position [m] and angle [rad] by which Levenberg-Marquardt IK from home, joints clamped to their limits, ends
    away from each pose [P]."""
    P = len(poses)
    q = torch.tensor([PANDA_HOME] * P, dtype=torch.float64)
    lo, hi = torch.tensor(PANDA_LIMITS.q_min) + 1e-3, torch.tensor(PANDA_LIMITS.q_max) - 1e-3
    pos_d = torch.tensor(np.array([p.pos for p in poses]), dtype=torch.float64)
    rot_d = torch.tensor(np.array([p.rot for p in poses]), dtype=torch.float64)
    eye = torch.eye(6, dtype=torch.float64)
    damping = torch.full((P, 1, 1), 1e-2, dtype=torch.float64)
    k, err = _pose_error(model, q, pos_d, rot_d)
    J = k.jac
    for _ in range(iterations):
        step = J.transpose(1, 2) @ torch.linalg.solve(J @ J.transpose(1, 2) + damping * eye, err.unsqueeze(-1))
        q_try = torch.minimum(torch.maximum(q + step.squeeze(-1), lo), hi)
        k_try, err_try = _pose_error(model, q_try, pos_d, rot_d)
        better = err_try.norm(dim=-1) < err.norm(dim=-1)  # a step kept only where it helps; else more damping
        q = torch.where(better[:, None], q_try, q)
        err = torch.where(better[:, None], err_try, err)
        J = torch.where(better[:, None, None], k_try.jac, J)
        damping = torch.where(better[:, None, None], damping / 3.0, damping * 4.0).clamp(1e-9, 1e3)
        if ((err.norm(dim=-1) < 1e-9) | (damping.flatten() >= 1e3)).all():  # at the pose, or stuck short of it
            break
    pos, rot = model.fk(q)
    cos = ((rot.transpose(1, 2) @ rot_d).diagonal(dim1=1, dim2=2).sum(-1) - 1.0) / 2.0
    return (pos - pos_d).norm(dim=-1).numpy(), torch.arccos(cos.clamp(-1.0, 1.0)).numpy()


def reach_warning(pcfg: PandaEnvConfig) -> str | None:
    """A line naming the scene's key poses out of the arm's reach (config keys included), else None."""
    model = PandaModel(tool=SCENES[pcfg.scene].tool)
    home_pos, home_rot = (x[0].numpy() for x in model.fk(torch.tensor([PANDA_HOME], dtype=torch.float64)))
    poses = key_poses(pcfg, home_pos, home_rot)
    miss_pos, miss_rot = ik_miss(model, poses)
    worst: dict[str, tuple[float, float, KeyPose]] = {}  # per named pose, its farthest miss
    for p, d, a in zip(poses, miss_pos, miss_rot):
        if (d > POSITION_TOLERANCE or a > ROTATION_TOLERANCE) and d >= worst.get(p.name, (-1.0,))[0]:
            worst[p.name] = (float(d), float(a), p)
    out = [f"{name} at ({', '.join(f'{v:.3f}' for v in p.pos)}) m: IK ends {1e3 * d:.0f} mm, {np.degrees(a):.1f} deg "
           "from it" for name, (d, a, p) in worst.items()]
    if not out:
        return None
    keys = poses[0].keys
    return (f"warning: the {pcfg.scene} scene asks for poses the arm cannot reach within its joint limits, so its "
            f"trials will fail (check {keys}): " + "; ".join(out))
