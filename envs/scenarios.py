"""Simulated operator and scripted scene procedures for the Panda env (paper 000, section VI): peg-in-hole, polishing,
free guidance.

Everything is batched over N arms with numpy (one array per quantity, loops over phases, never over arms) and runs
at the agent rate (100 Hz) except `Operator.wrench`, which the env calls every 1 kHz control period.

Frames: positions and rotations are those of PandaSim's arm frame (each arm's own base frame), world-aligned.
The scenes write the Cartesian reference of the control site (the tool tip "tcp": pos_d [N, 3], rot_d [N, 3, 3]) and
start operator intents; they also keep the per-trial metrics the evaluation reports.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from a3cqp_rl.config import GuidanceConfig, OperatorConfig, PegInHoleConfig, PolishingConfig
from a3cqp_rl.control.frames import rotation_log
from a3cqp_rl.robot.scenes import HoleGeometry, hole_block_xml, plate_xml

__all__ = ["Operator", "SceneInput", "Scene", "PegInHole", "Polishing", "Guidance", "make_scene", "min_jerk",
           "rotvec_to_matrix", "turn_about_vertical", "SCENES"]


def min_jerk(t: np.ndarray, duration: float | np.ndarray) -> np.ndarray:
    """Minimum-jerk progress s ∈ [0, 1] at time t of a move lasting `duration` [s] (10τ³ − 15τ⁴ + 6τ⁵)."""
    tau = np.clip(t / np.maximum(duration, 1e-9), 0.0, 1.0)
    return tau * tau * tau * (10.0 + tau * (-15.0 + 6.0 * tau))


def turn_about_vertical(v: np.ndarray, angle: np.ndarray | float) -> np.ndarray:
    """Vectors v [..., 2 or 3] (x, y[, z]; m) turned about the vertical z by `angle` [rad], which broadcasts against
    v[..., 0]; z is kept."""
    c, s = np.cos(angle), np.sin(angle)
    out = np.array(v, dtype=np.float64)
    out[..., 0], out[..., 1] = c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1]
    return out


def rotvec_to_matrix(v: np.ndarray) -> np.ndarray:
    """Rotation matrices [..., 3, 3] of rotation vectors [..., 3] (rad), Rodrigues' formula."""
    theta = np.linalg.norm(v, axis=-1)[..., None, None]
    k = v / np.maximum(theta[..., 0], 1e-12)
    K = np.zeros(v.shape[:-1] + (3, 3))
    K[..., 0, 1], K[..., 0, 2], K[..., 1, 2] = -k[..., 2], k[..., 1], -k[..., 0]
    K = K - np.swapaxes(K, -1, -2)
    return np.eye(3) + np.sin(theta) * K + (1.0 - np.cos(theta)) * (K @ K)


def _interp_rot(r0: np.ndarray, r1: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Geodesic interpolation from r0 to r1 [k, 3, 3] at progress s [k]."""
    return rotvec_to_matrix(s[:, None] * rotation_log(r1 @ np.swapaxes(r0, -1, -2))) @ r0


def _clip_norm(v: np.ndarray, bound: float) -> np.ndarray:
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return v * np.minimum(1.0, bound / np.maximum(n, 1e-12))


# ---------------------------------------------------------------------------------------------------- operator
class Operator:
    """N operator hands (OperatorConfig): each grasps the handle on an intent, pulls toward a goal, releases.

    States per arm: idle, holding (force fades in, attractor moves to the goal), releasing (force fades out).
    `wrench()` is called every control period with the handle's current state and returns the hand's force and
    torque [N, 3] (world frame) to apply at the handle; it acts on the state `delay` s ago (reaction delay).
    """

    IDLE, HOLD, RELEASE = 0, 1, 2

    def __init__(self, n: int, cfg: OperatorConfig, dt: float) -> None:
        self.n, self.cfg, self.dt = n, cfg, dt
        self.state = np.zeros(n, dtype=np.int64)
        self.t_grasp = np.zeros(n)
        self.t_release = np.zeros(n)
        self.t_reached = np.full(n, np.nan)
        self.start = np.zeros((n, 3))
        self.goal = np.zeros((n, 3))
        self.rot_grasp = np.tile(np.eye(3), (n, 1, 1))
        self.releases = np.zeros(n, dtype=np.int64)
        """Number of completed grasps per arm (a scene sees a release as this count going up)."""
        self.reached = np.zeros(n, dtype=bool)
        """Whether the last grasp reached its goal before releasing."""
        self.force_scale = np.ones(n)
        """Per-arm factor on the hand's stiffness, damping and force/torque bounds (1 = the config's operator; the
        robustness trials of NSGA-II's Panda objective draw it per trial)."""
        self._lag = max(1, int(round(cfg.delay / dt)))
        self._hist = np.zeros((self._lag, n, 18))  # ring buffer of (p, v, R, ω) of the handle
        self._k = 0
        self._primed = np.zeros(n, dtype=bool)
        self._last_pos = np.zeros((n, 3))
        self._last_t = np.zeros(n)
        self._last_rot = np.tile(np.eye(3), (n, 1, 1))

    def reset(self, idx: np.ndarray) -> None:
        """Make arms `idx` idle with no history."""
        self.state[idx] = self.IDLE
        self.t_reached[idx] = np.nan
        self.releases[idx] = 0
        self.reached[idx] = False
        self._primed[idx] = False

    @property
    def active(self) -> np.ndarray:
        """Bool [N]: the hand is on the handle (holding or releasing)."""
        return self.state != self.IDLE

    def grasp(self, idx: np.ndarray, goal: np.ndarray, t: np.ndarray) -> None:
        """Start an intent for arms `idx`: grasp at the handle's last position, move it to `goal` [k, 3] (arm frame)."""
        if len(idx) == 0:
            return
        self.state[idx] = self.HOLD
        self.t_grasp[idx] = t[idx]
        self.t_reached[idx] = np.nan
        self.start[idx] = self._last_pos[idx]
        self.rot_grasp[idx] = self._last_rot[idx]  # the grip keeps the orientation the tool had when grasped
        self.goal[idx] = goal
        self.reached[idx] = False

    def attractor(self, t: np.ndarray) -> np.ndarray:
        """Where each hand pulls the handle to [N, 3]: from the grasp point toward the goal at `speed`."""
        return self._attractor(t, slice(None))

    def _attractor(self, t: np.ndarray, arms: np.ndarray | slice) -> np.ndarray:
        """`attractor` of `arms` (`t`: their times)."""
        start = self.start[arms]
        path = self.goal[arms] - start
        length = np.linalg.norm(path, axis=1)
        s = ((t - self.t_grasp[arms]) * self.cfg.speed / np.maximum(length, 1e-9)).clip(0.0, 1.0)
        return start + s[:, None] * path

    def update(self, t: np.ndarray, handle_pos: np.ndarray, handle_rot: np.ndarray) -> None:
        """Agent-rate bookkeeping: goal reached -> hold -> release; timeouts; release fade-out ends."""
        c = self.cfg
        still = True
        if c.release_speed > 0:  # the handle's speed over the last agent period
            speed = np.linalg.norm(handle_pos - self._last_pos, axis=1) / np.maximum(t - self._last_t, 1e-9)
            still = speed < c.release_speed
        self._last_pos[:] = handle_pos
        self._last_rot[:] = handle_rot
        self._last_t[:] = t
        hold = self.state == self.HOLD
        near = hold & (np.linalg.norm(handle_pos - self.goal, axis=1) < c.goal_tolerance) & np.isnan(self.t_reached)
        self.t_reached[near] = t[near]
        self.reached[near] = True
        done_hold = hold & ((((t - self.t_reached) >= c.hold_time) & still) | ((t - self.t_grasp) >= c.timeout))
        self.state[done_hold] = self.RELEASE
        self.t_release[done_hold] = t[done_hold]
        done = (self.state == self.RELEASE) & ((t - self.t_release) >= c.grip_time)
        self.state[done] = self.IDLE
        self.releases[done] += 1

    def wrench(self, t: np.ndarray, pos: np.ndarray, vel: np.ndarray, rot: np.ndarray, omega: np.ndarray,
               noise: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Hand force and torque [N, 3] (N, N m; world) from the handle's state (pos, vel, rot, ω) `delay` s ago and
        its present velocity (the intrinsic damping); `noise` [N, 3]: standard normal draws for the tremor (scaled by
        `noise` of the config)."""
        c, k = self.cfg, self._k
        if not self._primed.all():  # no history yet: the hand sees the present
            fresh = ~self._primed
            self._hist[:, fresh] = np.concatenate([pos, vel, rot.reshape(-1, 9), omega], axis=1)[fresh]
            self._primed[fresh] = True
        on = np.flatnonzero(self.state != self.IDLE)  # only the hands on a handle (a few arms of a batch at a time)
        old = self._hist[k, on]  # (a copy: read before the slot takes the present)
        slot = self._hist[k]
        slot[:, :3], slot[:, 3:6], slot[:, 6:15], slot[:, 15:] = pos, vel, rot.reshape(-1, 9), omega
        self._k = (k + 1) % self._lag
        force, torque = np.zeros((self.n, 3)), np.zeros((self.n, 3))
        if not len(on):
            return force, torque
        t = t[on]
        p, v, R, w = old[:, :3], old[:, 3:6], old[:, 6:15].reshape(-1, 3, 3), old[:, 15:]
        # (the .clip methods: np.clip's overhead is ~3 µs more)
        grip = np.where(self.state[on] == self.HOLD, ((t - self.t_grasp[on]) / c.grip_time).clip(0.0, 1.0),
                        (1.0 - (t - self.t_release[on]) / c.grip_time).clip(0.0, 1.0))[:, None]
        s = self.force_scale[on, None]
        f = s * (c.stiffness * (self._attractor(t, on) - p) - c.damping * v)
        if c.intrinsic_damping > 0:  # the muscles' damping acts on the present velocity
            f = f - s * c.intrinsic_damping * vel[on]
        if c.noise > 0 and noise is not None:
            f = f + c.noise * noise[on]
        tq = s * (c.rot_stiffness * rotation_log(self.rot_grasp[on] @ np.swapaxes(R, -1, -2)) - c.rot_damping * w)
        force[on], torque[on] = _clip_norm(grip * f, c.max_force * s), _clip_norm(grip * tq, c.max_torque * s)
        return force, torque


# ---------------------------------------------------------------------------------------------------- scenes
@dataclass
class SceneInput:
    """What a scene reads at the agent rate (arm frame, control site = tool tip)."""

    t: np.ndarray
    """Episode time of each arm [N] (s)."""
    pos: np.ndarray
    """Tool tip position [N, 3] (m)."""
    rot: np.ndarray
    """Tool tip rotation [N, 3, 3] (columns: local axes L)."""
    f_env: np.ndarray
    """Environment wrench at the tool tip [N, 6] (world; N, N m), as the simulation has it: without the sensors'
    noise and bias (PandaEnv.f_env_true)."""
    f_ope: np.ndarray
    """Operator wrench estimate f_ext − f_env at the tool tip [N, 6] (world)."""
    f_d: np.ndarray
    """Desired local wrench f_d^L [N, 6] in use."""
    handle_pos: np.ndarray
    """Operator handle position [N, 3]."""


class Scene:
    """A scripted procedure for N arms: reference pose, operator intents, phases and per-trial metrics."""

    name = "scene"
    tool = "peg_mesh"
    phase_names: tuple[str, ...] = ()
    """Phase labels; `phase` holds indices into it."""
    phase_task: tuple[str, ...] = ()
    """Which task the phase expects to lead ("IK", "FC", "AC"): the shading of the episode plot."""

    def __init__(self, n: int, operator: Operator, home_pos: np.ndarray, home_rot: np.ndarray) -> None:
        self.n, self.operator = n, operator
        self.home_pos, self.home_rot = home_pos.copy(), home_rot.copy()
        self.pos_d = np.tile(home_pos, (n, 1))
        self.rot_d = np.tile(home_rot, (n, 1, 1))
        self.phase = np.zeros(n, dtype=np.int64)
        self.done = np.zeros(n, dtype=bool)
        self.t0 = np.zeros(n)

    def mjcf(self) -> str:
        """Scene bodies for PandaSim."""
        raise NotImplementedError

    def rest_time(self) -> float:
        """How long an episode starts with the arm resting at home, untouched [s] (where the sensors can be tared)."""
        raise NotImplementedError

    def reset(self, idx: np.ndarray, rngs: list[np.random.Generator]) -> None:
        """Start a new trial for arms `idx`, drawing its random parameters from the arms' own generators `rngs`
        (one per entry of idx: a trial depends on its arm's stream only, whatever the batch)."""
        self.pos_d[idx], self.rot_d[idx] = self.home_pos, self.home_rot
        self.phase[idx] = 0
        self.done[idx] = False
        self.t0[idx] = 0.0

    def update(self, inp: SceneInput) -> None:
        """Advance the procedure one agent period: phases, reference, operator intents, metrics."""
        raise NotImplementedError

    def abort(self, idx: np.ndarray) -> None:
        """End the trials of arms `idx` now (their simulation diverged): last phase, reference home."""
        self.phase[idx] = len(self.phase_names) - 1
        self.done[idx] = True
        self.pos_d[idx], self.rot_d[idx] = self.home_pos, self.home_rot

    def metrics(self) -> dict[str, np.ndarray]:
        """Per-arm metrics of the current trials (arrays [N] or [N, cycles])."""
        return {}

    def body_offsets(self) -> dict[str, np.ndarray]:
        """Static scene bodies (MJCF name) the trials move, each arm's offset [N, 3] (m, world) from where `mjcf`
        puts it (PandaSim.move_static_body, at every reset)."""
        return {}

    def signals(self, inp: SceneInput) -> dict[str, np.ndarray]:
        """Scene-specific per-step signals for plots (e.g. the peg's misalignment), arrays [N]."""
        return {}

    def reward_term(self) -> np.ndarray | None:
        """A task reward [N] added to eq. 30 on every axis at this agent period (None: none)."""
        return None

    def _enter(self, mask: np.ndarray, phase: int, t: np.ndarray) -> None:
        self.phase[mask] = phase
        self.t0[mask] = t[mask]

    def _add_operator_force(self, acc: dict[str, np.ndarray], keys: tuple[str, str, str], a: np.ndarray,
                            inp: SceneInput) -> None:
        """Add |f_ope| [N] of arms `a` while their operator holds to the count, sum and peak named by `keys`."""
        n, total, peak = keys
        hold = self.operator.active[a]
        f = np.where(hold, np.linalg.norm(inp.f_ope[a, :3], axis=1), 0.0)
        acc[n][a] += hold
        acc[total][a] += f
        acc[peak][a] = np.maximum(acc[peak][a], f)


class PegInHole(Scene):
    """Peg-in-hole (paper 000, Fig. 7, Table VI); see PegInHoleConfig for the procedure."""

    name, tool = "peg_in_hole", "peg_mesh"
    SETTLE, APPROACH, INSERT, DISENGAGE, RETURN, DONE = range(6)
    phase_names = ("settle", "approach", "insert", "disengage", "return", "done")
    phase_task = ("IK", "IK", "FC", "AC", "IK", "IK")
    BORE_DEPTH = 0.001
    """Depth below the rim [m] from which a tip within the bore's radius counts as in the bore (the insertion time's
    split: first contact -> in the bore, set by the x-y alignment; in the bore -> success, by the push along z)."""

    def __init__(self, n: int, operator: Operator, home_pos: np.ndarray, home_rot: np.ndarray,
                 cfg: PegInHoleConfig) -> None:
        super().__init__(n, operator, home_pos, home_rot)
        self.cfg = cfg
        self.geometry = HoleGeometry(center=tuple(cfg.hole_center), top=cfg.hole_top, bore_diameter=cfg.hole_diameter,
                                     depth=cfg.hole_depth, segments=cfg.hole_segments, friction=cfg.friction)
        self.hole = np.array([cfg.hole_center[0], cfg.hole_center[1], cfg.hole_top])
        C = cfg.cycles
        self.cycle = np.zeros(n, dtype=np.int64)
        self.offset = np.zeros((n, C, 3))  # approach-pose offset from the hole axis, per cycle
        self.tilt = np.zeros((n, C, 3))  # approach-pose tilt (rotation vector), per cycle
        self.from_pos, self.from_rot = self.pos_d.copy(), self.rot_d.copy()
        self.contact_time = np.full((n, C), np.nan)
        """Episode time of the first contact of each cycle [s]."""
        self.success_time = np.full((n, C), np.nan)
        """Episode time at which the peg reached `success_depth` [s]."""
        self.misalign_translation = np.full((n, C), np.nan)
        """Horizontal distance of the peg tip from the hole axis at the first contact [m]."""
        self.misalign_rotation = np.full((n, C), np.nan)
        """Angle between the peg axis and the hole axis at the first contact [rad]."""
        self.max_depth = np.full((n, C), np.nan)
        """Deepest tip position below the rim during the insertion [m]."""
        self.bore_time = np.full((n, C), np.nan)
        """Episode time at which the tip, after the first contact, was first `BORE_DEPTH` inside the bore [s]."""
        self.extracted = np.zeros((n, C), dtype=bool)
        """Whether the peg left the hole (tip above the rim) during the disengagement."""
        self.in_bore_at_grasp = np.zeros((n, C), dtype=bool)
        """Whether the tip was in the bore (below the rim, within its radius) when the operator grasped to disengage:
        the disengagements that can pull a peg out (a peg that never entered is 'out' from the start)."""
        self.disengage_force = np.full((n, C), np.nan)
        """Mean |f_ope| while the operator disengages [N]."""
        self._f_sum, self._f_cnt = np.zeros(n), np.zeros(n)
        self._grasp_releases = np.zeros(n, dtype=np.int64)

    def mjcf(self) -> str:
        return hole_block_xml(self.geometry)

    def rest_time(self) -> float:
        return self.cfg.settle_time

    def reference_depth(self, tau: np.ndarray) -> np.ndarray:
        """Depth below the rim [k] (m) of the insertion reference `tau` s after the insertion phase began: minimum-jerk
        from the approach height to the rim in `descent_time`, then down at `insert_speed` to `insert_depth`."""
        c = self.cfg
        above = -c.approach_height * (1.0 - min_jerk(tau, c.descent_time))
        below = np.clip((tau - c.descent_time) * c.insert_speed, 0.0, c.insert_depth)
        return above + below

    def reset(self, idx: np.ndarray, rngs: list[np.random.Generator]) -> None:
        super().reset(idx, rngs)
        c, C = self.cfg, self.cfg.cycles
        self.cycle[idx] = 0
        # translation: |offset| ~ N(mean, std) clipped >= 0, uniform direction; tilt: |θ| ~ N, random horizontal axis
        draws = np.array([[rng.normal(c.misalign_translation[0], c.misalign_translation[1], C),
                           rng.uniform(0.0, 2.0 * np.pi, C),
                           np.radians(rng.normal(c.misalign_rotation_deg[0], c.misalign_rotation_deg[1], C)),
                           rng.uniform(0.0, 2.0 * np.pi, C)] for rng in rngs])  # [k, 4, C]
        mag, ang, tilt, axis = np.maximum(draws[:, 0], 0.0), draws[:, 1], np.maximum(draws[:, 2], 0.0), draws[:, 3]
        self.offset[idx] = np.stack([mag * np.cos(ang), mag * np.sin(ang), np.zeros_like(mag)], axis=-1)
        self.tilt[idx] = np.stack([tilt * np.cos(axis), tilt * np.sin(axis), np.zeros_like(tilt)], axis=-1)
        self.from_pos[idx], self.from_rot[idx] = self.home_pos, self.home_rot
        for a in (self.contact_time, self.success_time, self.misalign_translation, self.misalign_rotation,
                  self.max_depth, self.bore_time, self.disengage_force):
            a[idx] = np.nan
        self.extracted[idx] = False
        self.in_bore_at_grasp[idx] = False
        self._f_sum[idx], self._f_cnt[idx] = 0.0, 0.0

    def _approach_pose(self, arms: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        cyc = self.cycle[arms]
        pos = self.hole + self.offset[arms, cyc] + np.array([0.0, 0.0, self.cfg.approach_height])
        rot = rotvec_to_matrix(self.tilt[arms, cyc]) @ self.home_rot
        return pos, rot

    def depth(self, pos: np.ndarray) -> np.ndarray:
        """Tip depth below the rim [N] (m; negative above)."""
        return self.hole[2] - pos[:, 2]

    def update(self, inp: SceneInput) -> None:
        c, t, ph = self.cfg, inp.t, self.phase
        arms = np.arange(self.n)
        depth = self.depth(inp.pos)
        # --- settle at home
        m = (ph == self.SETTLE) & (t - self.t0 >= c.settle_time)
        if m.any():
            self.from_pos[m], self.from_rot[m] = self.pos_d[m], self.rot_d[m]
            self._enter(m, self.APPROACH, t)
        # --- approach pose (misaligned), reached within the lenient tolerance
        m = ph == self.APPROACH
        if m.any():
            a = arms[m]
            goal_p, goal_r = self._approach_pose(a)
            s = min_jerk(t[a] - self.t0[a], c.approach_time)
            self.pos_d[a] = self.from_pos[a] + s[:, None] * (goal_p - self.from_pos[a])
            self.rot_d[a] = _interp_rot(self.from_rot[a], goal_r, s)
            err = np.linalg.norm(goal_p - inp.pos[a], axis=1)
            late = t[a] - self.t0[a] >= c.approach_time
            go = a[late & ((err < c.approach_tolerance) | (t[a] - self.t0[a] >= c.approach_time + 3.0))]
            if len(go):
                self.from_pos[go], self.from_rot[go] = goal_p[np.isin(a, go)], goal_r[np.isin(a, go)]
                self._enter(np.isin(arms, go), self.INSERT, t)
        # --- insertion: reference to the contact pose (z fast, x-y and tilt slow); contact, success, time limit
        m = ph == self.INSERT
        if m.any():
            a = arms[m]
            cyc = self.cycle[a]
            tau = t[a] - self.t0[a]
            sxy = min_jerk(tau, c.align_time)
            p = self.from_pos[a]
            self.pos_d[a, :2] = p[:, :2] + sxy[:, None] * (self.hole[:2] - p[:, :2])
            self.pos_d[a, 2] = self.hole[2] - self.reference_depth(tau)
            self.rot_d[a] = _interp_rot(self.from_rot[a], np.broadcast_to(self.home_rot, (len(a), 3, 3)), sxy)
            touching = np.linalg.norm(inp.f_env[a, :3], axis=1) > c.contact_force
            first = touching & np.isnan(self.contact_time[a, cyc])
            if first.any():
                f = a[first]
                self.contact_time[f, cyc[first]] = t[f]
                self.misalign_translation[f, cyc[first]] = np.linalg.norm(inp.pos[f, :2] - self.hole[:2], axis=1)
                # angle between the tool axis (local z) and the hole axis (world −z)
                self.misalign_rotation[f, cyc[first]] = np.arccos(np.clip(-inp.rot[f, 2, 2], -1.0, 1.0))
            self.max_depth[a, cyc] = np.fmax(self.max_depth[a, cyc], depth[a])
            contacted = ~np.isnan(self.contact_time[a, cyc])
            # inserted: deep enough with the tip inside the bore (not slid down beside the block)
            inside = np.linalg.norm(inp.pos[a, :2] - self.hole[:2], axis=1) < 0.5 * c.hole_diameter
            entered = contacted & inside & (depth[a] >= self.BORE_DEPTH) & np.isnan(self.bore_time[a, cyc])
            self.bore_time[a[entered], cyc[entered]] = t[a[entered]]
            ok = contacted & (depth[a] >= c.success_depth) & inside
            self.success_time[a[ok], cyc[ok]] = t[a[ok]]
            since = np.where(contacted, t[a] - self.contact_time[a, cyc], tau - c.descent_time)
            over = ok | (since > c.time_limit)
            if c.operator_disengage and c.cycles == 1 and not c.disengage_failed:
                # a single trial whose peg is not in by the time limit ends there: its metrics are final and no
                # next approach needs the block cleared (the operator would pull at an arm that may not yield)
                failed = np.isin(arms, a[over & ~ok])
                self._enter(failed, self.DONE, t)
                self.done[failed] = True
                over &= ok
            finished = a[over]
            if len(finished):
                fm = np.isin(arms, finished)
                if c.operator_disengage:
                    self.in_bore_at_grasp[finished, cyc[over]] = (depth[finished] > 0.0) & inside[over]
                    self._grasp_releases[fm] = self.operator.releases[fm]
                    goal = inp.handle_pos[fm] + np.array([0.0, 0.0, c.disengage_lift])
                    self.operator.grasp(arms[fm], goal, t)
                    self._f_sum[fm], self._f_cnt[fm] = 0.0, 0.0
                    self._enter(fm, self.DISENGAGE, t)
                else:
                    self._start_return(fm, t)
        # --- the operator pulls the peg out; the reference stays (Fig. 7)
        m = ph == self.DISENGAGE
        if m.any():
            a = arms[m]
            cyc = self.cycle[a]
            holding = self.operator.active[a]
            self._f_sum[a] += np.where(holding, np.linalg.norm(inp.f_ope[a, :3], axis=1), 0.0)
            self._f_cnt[a] += holding
            self.extracted[a, cyc] |= depth[a] < 0.0
            released = self.operator.releases[a] > self._grasp_releases[a]
            if released.any():
                r = a[released]
                self.disengage_force[r, self.cycle[r]] = self._f_sum[r] / np.maximum(self._f_cnt[r], 1.0)
                self._start_return(np.isin(arms, r), t, inp.pos, inp.rot)
        # --- back home; then the next cycle or done
        m = ph == self.RETURN
        if m.any():
            a = arms[m]
            s = min_jerk(t[a] - self.t0[a], c.return_time)
            self.pos_d[a] = self.from_pos[a] + s[:, None] * (self.home_pos - self.from_pos[a])
            self.rot_d[a] = _interp_rot(self.from_rot[a], np.broadcast_to(self.home_rot, (len(a), 3, 3)), s)
            self.extracted[a, self.cycle[a]] |= depth[a] < 0.0
            end = a[t[a] - self.t0[a] >= c.return_time]
            if len(end):
                em = np.isin(arms, end)
                more = em & (self.cycle + 1 < c.cycles)
                if c.restart_needs_extraction:  # a peg still in the bore ends the episode (no dragging it away)
                    more &= self.extracted[np.arange(len(self.cycle)), self.cycle]
                self.cycle[more] += 1
                self.from_pos[more], self.from_rot[more] = self.pos_d[more], self.rot_d[more]
                self._enter(more, self.APPROACH, t)
                self._enter(em & ~more, self.DONE, t)
                self.done[em & ~more] = True

    def _start_return(self, mask: np.ndarray, t: np.ndarray, pos: np.ndarray | None = None,
                      rot: np.ndarray | None = None) -> None:
        """Arms `mask` go home from their reference, or from the measured pose `pos`, `rot` [N, ...] where the
        operator let go (the reference stayed at the inserted pose while they pulled: starting from it would drive
        the peg back into the bore)."""
        src_p, src_r = (self.pos_d, self.rot_d) if pos is None else (pos, rot)
        self.from_pos[mask], self.from_rot[mask] = src_p[mask], src_r[mask]
        if self.cfg.cycles == 1 and self.cfg.operator_disengage:  # a single trial ends when the operator lets go
            self._enter(mask, self.DONE, t)
            self.done[mask] = True
        else:
            self._enter(mask, self.RETURN, t)

    def metrics(self) -> dict[str, np.ndarray]:
        succ = ~np.isnan(self.success_time)
        return {"success": succ, "insertion_time": self.success_time - self.contact_time,
                "time_limit": np.full(succ.shape, self.cfg.time_limit), "contact_time": self.contact_time.copy(),
                "misalign_translation": self.misalign_translation.copy(),
                "misalign_rotation": self.misalign_rotation.copy(), "max_depth": self.max_depth.copy(),
                "to_bore_time": self.bore_time - self.contact_time,
                "bore_descent_time": self.success_time - self.bore_time,
                "extracted": self.extracted.copy(), "in_bore_at_grasp": self.in_bore_at_grasp.copy(),
                "disengage_force": self.disengage_force.copy()}

    def reward_term(self) -> np.ndarray | None:
        if self.cfg.time_cost == 0.0:
            return None
        started = ~np.isnan(self.contact_time[np.arange(self.n), self.cycle])
        return -self.cfg.time_cost * ((self.phase == self.INSERT) & started)

    def signals(self, inp: SceneInput) -> dict[str, np.ndarray]:
        return {"misalign_translation": np.linalg.norm(inp.pos[:, :2] - self.hole[:2], axis=1),
                "misalign_rotation": np.arccos(np.clip(-inp.rot[:, 2, 2], -1.0, 1.0)),
                "depth": self.depth(inp.pos)}


class Polishing(Scene):
    """Polishing (paper 000, Fig. 8); see PolishingConfig. Metrics over the full circles of the polishing phases:
    fraction of samples in contact, mean pressing force and mean |pressing force − f_d| (every sample, in contact or
    not), x-y tracking error (RMS); mean |f_ope| while the operator relocates the zone, and how often the hand
    reached its relocation goal."""

    name, tool = "polishing", "disc_mesh"
    REST, APPROACH, POLISH, RELOCATE, HOLD, DONE = range(6)
    phase_names = ("rest", "approach", "polish", "relocate", "hold", "done")
    phase_task = ("IK", "IK", "FC", "AC", "IK", "IK")
    RAMP = 1.0
    """Seconds over which the circle's radius grows from 0 (so the reference starts where the tool is)."""
    DISC_RADIUS = 0.0625
    """Radius of the polishing disc of tool_disc_mesh.xml [m]."""

    def __init__(self, n: int, operator: Operator, home_pos: np.ndarray, home_rot: np.ndarray,
                 cfg: PolishingConfig) -> None:
        super().__init__(n, operator, home_pos, home_rot)
        self.cfg = cfg
        self.zone = np.zeros((n, 2))
        self.period = np.zeros(n, dtype=np.int64)
        self.from_pos = self.pos_d.copy()
        self._releases = np.zeros(n, dtype=np.int64)
        K = len(cfg.relocations)
        # accumulators per arm: polishing samples, in-contact samples, |f_env,z − f_d,z| sum, tracking error² sum,
        # relocation |f_ope| sum and count, peak relocation |f_ope|
        self._acc = {k: np.zeros(n) for k in ("n_pol", "n_con", "f_err", "f_con", "trk2", "n_rel", "f_rel", "f_rel_max")}
        self.zone_reached = np.zeros((n, K), dtype=bool)
        """Whether the operator's hand reached each relocation goal."""
        self.plate_offset = np.zeros((n, 3))
        """The trial's plate offset from where the MJCF puts it [m] (z: its unknown height)."""
        self.turn = np.zeros(n)
        """The trial's turn of the operator's moves about the vertical [rad]."""

    def mjcf(self) -> str:
        c = self.cfg
        return plate_xml(center=tuple(c.plate_center), top=c.plate_top, half_size=tuple(c.plate_half_size),
                         friction=c.friction, tool_geom="disc", friction_solref=tuple(c.friction_solref))

    def rest_time(self) -> float:
        return self.cfg.rest_time

    def reset(self, idx: np.ndarray, rngs: list[np.random.Generator]) -> None:
        super().reset(idx, rngs)
        c = self.cfg
        # four draws per trial whatever the spreads (one spread set to 0 leaves the others' trials as they were)
        u = np.array([(r.standard_normal(), *r.random(3)) for r in rngs]).reshape(len(idx), 4)
        dz = c.plate_top_spread * np.clip(u[:, 0], -2.0, 2.0)
        self.plate_offset[idx] = np.stack([np.zeros_like(dz), np.zeros_like(dz), dz], axis=1)
        rho, phi = c.zone_spread * np.sqrt(u[:, 1]), 2.0 * np.pi * u[:, 2]  # uniform in the disc
        self.zone[idx] = (np.array(c.plate_center) + np.array(c.start_offset)
                          + np.stack([rho * np.cos(phi), rho * np.sin(phi)], axis=1))
        self.turn[idx] = np.deg2rad(c.relocation_turn_deg) * (2.0 * u[:, 3] - 1.0)
        self.period[idx] = 0
        self.from_pos[idx] = self.home_pos
        for v in self._acc.values():
            v[idx] = 0.0
        self.zone_reached[idx] = False

    def _polish_z(self) -> float:
        return self.cfg.plate_top - self.cfg.preload

    def update(self, inp: SceneInput) -> None:
        c, t, ph, arms = self.cfg, inp.t, self.phase, np.arange(self.n)
        m = (ph == self.REST) & (t - self.t0 >= c.rest_time)
        if m.any():
            self.from_pos[m] = self.pos_d[m]
            self._enter(m, self.APPROACH, t)
        m = ph == self.APPROACH
        if m.any():
            a = arms[m]
            goal = np.concatenate([self.zone[a], np.full((len(a), 1), self._polish_z())], axis=1)
            s = min_jerk(t[a] - self.t0[a], c.approach_time)
            self.pos_d[a] = self.from_pos[a] + s[:, None] * (goal - self.from_pos[a])
            self.rot_d[a] = self.home_rot
            self._enter(m & (t - self.t0 >= c.approach_time), self.POLISH, t)
        m = ph == self.POLISH
        if m.any():
            a = arms[m]
            tau = t[a] - self.t0[a]
            rho = c.circle_radius * np.clip(tau / self.RAMP, 0.0, 1.0)
            ang = 2.0 * np.pi * tau / c.circle_period
            self.pos_d[a, 0] = self.zone[a, 0] + rho * np.sin(ang)
            self.pos_d[a, 1] = self.zone[a, 1] + rho * (1.0 - np.cos(ang))
            self.pos_d[a, 2] = self._polish_z()
            steady = tau >= self.RAMP  # metrics on the full circle only
            fz, fdz = inp.f_env[a, 2], inp.f_d[a, 2]  # the plate pushes the disc up (world +z): the pressing force
            con = fz > c.contact_force
            acc = self._acc
            acc["n_pol"][a] += steady
            acc["n_con"][a] += steady & con
            acc["f_err"][a] += np.where(steady, np.abs(fz - fdz), 0.0)  # every polishing sample, in contact or not
            acc["f_con"][a] += np.where(steady, fz, 0.0)
            acc["trk2"][a] += np.where(steady, np.sum((inp.pos[a, :2] - self.pos_d[a, :2]) ** 2, axis=1), 0.0)
            end = a[tau >= c.polish_time]
            if len(end):
                em = np.isin(arms, end)
                k = self.period[end]
                d = turn_about_vertical(np.array(c.relocations)[k], self.turn[end])
                goal = inp.handle_pos[end] + np.concatenate([d, np.full((len(end), 1), c.lift)], axis=1)
                self._releases[end] = self.operator.releases[end]
                self.operator.grasp(end, goal, t)
                self._enter(em, self.RELOCATE, t)
        m = ph == self.RELOCATE
        if m.any():
            a = arms[m]
            # while the operator guides, the reference follows the tool (Fig. 8: x_d changes with the operator)
            self.pos_d[a] = inp.pos[a]
            self._add_operator_force(self._acc, ("n_rel", "f_rel", "f_rel_max"), a, inp)
            released = self.operator.releases[a] > self._releases[a]
            if released.any():
                r = a[released]
                self.zone_reached[r, self.period[r]] = self.operator.reached[r]
                self._enter(np.isin(arms, r), self.HOLD, t)
        m = ph == self.HOLD
        if m.any():
            a = arms[m]
            end = a[t[a] - self.t0[a] >= c.hold_time]
            if len(end):
                em = np.isin(arms, end)
                self.period[end] += 1
                more = em & (self.period < len(c.relocations))
                # the new working zone is where the operator left the tool, kept on the plate (disc and circle inside)
                margin = np.array(c.plate_half_size) - (self.DISC_RADIUS + c.circle_radius + 0.01)
                centre = np.array(c.plate_center)
                self.zone[more] = np.clip(self.pos_d[more, :2], centre - np.maximum(margin, 0.0),
                                          centre + np.maximum(margin, 0.0))
                self.from_pos[more] = self.pos_d[more]
                self._enter(more, self.APPROACH, t)
                self._enter(em & ~more, self.DONE, t)
                self.done[em & ~more] = True

    def metrics(self) -> dict[str, np.ndarray]:
        a = self._acc
        n_pol = np.maximum(a["n_pol"], 1.0)
        return {"contact_fraction": a["n_con"] / n_pol,
                "force_error": np.where(a["n_pol"] > 0, a["f_err"] / n_pol, np.nan),
                "contact_force": np.where(a["n_pol"] > 0, a["f_con"] / n_pol, np.nan),
                "tracking_error": np.sqrt(a["trk2"] / np.maximum(a["n_pol"], 1.0)),
                "relocation_force": np.where(a["n_rel"] > 0, a["f_rel"] / np.maximum(a["n_rel"], 1.0), np.nan),
                "zones_reached": self.zone_reached.mean(axis=1)}

    def signals(self, inp: SceneInput) -> dict[str, np.ndarray]:
        return {"x_d": self.pos_d[:, 0].copy(), "y_d": self.pos_d[:, 1].copy()}

    def body_offsets(self) -> dict[str, np.ndarray]:
        return {"plate": self.plate_offset}


class Guidance(Scene):
    """Free guidance: the operator takes the tool to each waypoint and lets go; the robot holds the taught pose. Each
    trial can turn the waypoints about the vertical and move each within a ball (`waypoint_turn_deg`,
    `waypoint_spread`), so that trials differ by more than the hand's tremor.

    Metrics: |f_ope| while guiding (mean, peak: the effort), the hand's distance to its goal at release, the time
    to reach the goal, and how far the robot drifts from the taught pose after the release."""

    name, tool = "guidance", "peg_mesh"
    PAUSE, GUIDE, DONE = range(3)
    phase_names = ("pause", "guide", "done")
    phase_task = ("IK", "AC", "IK")

    def __init__(self, n: int, operator: Operator, home_pos: np.ndarray, home_rot: np.ndarray, cfg: GuidanceConfig,
                 handle_home: np.ndarray) -> None:
        super().__init__(n, operator, home_pos, home_rot)
        self.cfg, self.handle_home = cfg, handle_home.copy()
        K = len(cfg.waypoints)
        self.goals = np.tile(np.asarray(cfg.waypoints, dtype=np.float64), (n, 1, 1))
        """This trial's handle goals relative to the handle's position at home [N, K, 3] (m, arm frame)."""
        self.turn = np.zeros(n)
        """This trial's turn of the waypoints about the vertical [rad]."""
        self.k = np.zeros(n, dtype=np.int64)
        self._releases = np.zeros(n, dtype=np.int64)
        self.goal_error = np.full((n, K), np.nan)
        """Handle-to-goal distance when the hand let go [m]."""
        self.reach_time = np.full((n, K), np.nan)
        """Grasp to goal reached [s] (NaN: not reached)."""
        self.drift = np.zeros((n, K))
        """Largest distance of the tool tip from the taught pose during the pause after each release [m]."""
        self._acc = {k: np.zeros(n) for k in ("n", "f", "f_max")}

    def mjcf(self) -> str:
        return ""

    def rest_time(self) -> float:
        return self.cfg.pause

    def reset(self, idx: np.ndarray, rngs: list[np.random.Generator]) -> None:
        super().reset(idx, rngs)
        c = self.cfg
        w = np.asarray(c.waypoints, dtype=np.float64)
        if c.waypoint_turn_deg > 0 or c.waypoint_spread > 0:
            # 1 + 4K draws per trial whatever the spreads (one spread set to 0 leaves the other's draws as they were);
            # none with both at 0, so the fixed procedure keeps its trials' noise streams
            K = len(w)
            u = np.array([np.concatenate([r.random(1), r.standard_normal(3 * K), r.random(K)]) for r in rngs])
            u = u.reshape(len(idx), 1 + 4 * K)
            turn = np.deg2rad(c.waypoint_turn_deg) * (2.0 * u[:, 0] - 1.0)
            d = u[:, 1:1 + 3 * K].reshape(len(idx), K, 3)
            d /= np.maximum(np.linalg.norm(d, axis=-1, keepdims=True), 1e-12)
            rho = c.waypoint_spread * np.cbrt(u[:, 1 + 3 * K:])  # uniform in the ball
            self.turn[idx] = turn
            self.goals[idx] = turn_about_vertical(w + rho[..., None] * d, turn[:, None])
        else:
            self.goals[idx], self.turn[idx] = w, 0.0
        self.k[idx] = 0
        for a in (self.goal_error, self.reach_time):
            a[idx] = np.nan
        self.drift[idx] = 0.0
        for v in self._acc.values():
            v[idx] = 0.0

    def update(self, inp: SceneInput) -> None:
        c, t, ph, arms = self.cfg, inp.t, self.phase, np.arange(self.n)
        K = len(c.waypoints)
        m = ph == self.PAUSE
        if m.any():
            a = arms[m]
            prev = self.k[a] - 1
            was = prev >= 0
            if was.any():
                d = np.linalg.norm(inp.pos[a[was]] - self.pos_d[a[was]], axis=1)
                self.drift[a[was], prev[was]] = np.maximum(self.drift[a[was], prev[was]], d)
            go = a[t[a] - self.t0[a] >= c.pause]
            if len(go):
                gm = np.isin(arms, go)
                more = gm & (self.k < K)
                mo = arms[more]
                if len(mo):
                    goal = self.handle_home + self.goals[mo, self.k[mo]]
                    self._releases[mo] = self.operator.releases[mo]
                    self.operator.grasp(mo, goal, t)
                    self._enter(more, self.GUIDE, t)
                self._enter(gm & ~more, self.DONE, t)
                self.done[gm & ~more] = True
        m = ph == self.GUIDE
        if m.any():
            a = arms[m]
            self._add_operator_force(self._acc, ("n", "f", "f_max"), a, inp)
            if c.reference_follows:
                self.pos_d[a] = inp.pos[a]
            released = self.operator.releases[a] > self._releases[a]
            if released.any():
                r = a[released]
                k = self.k[r]
                self.goal_error[r, k] = np.linalg.norm(inp.handle_pos[r] - self.operator.goal[r], axis=1)
                self.reach_time[r, k] = self.operator.t_reached[r] - self.operator.t_grasp[r]
                self.pos_d[r], self.rot_d[r] = inp.pos[r], inp.rot[r]  # the released pose is the new reference
                self.k[r] += 1
                self._enter(np.isin(arms, r), self.PAUSE, t)

    def metrics(self) -> dict[str, np.ndarray]:
        a = self._acc
        return {"guide_force": np.where(a["n"] > 0, a["f"] / np.maximum(a["n"], 1.0), np.nan),
                "guide_force_peak": a["f_max"].copy(), "goal_error": self.goal_error.copy(),
                "reach_time": self.reach_time.copy(), "drift": self.drift.copy()}


SCENES = {"peg_in_hole": PegInHole, "polishing": Polishing, "guidance": Guidance}


def make_scene(name: str, n: int, operator: Operator, home_pos: np.ndarray, home_rot: np.ndarray, cfg,  # noqa: ANN001
               handle_home: np.ndarray) -> Scene:
    """The scene `name` for n arms (cfg: the PandaEnvConfig holding its section)."""
    if name == "peg_in_hole":
        return PegInHole(n, operator, home_pos, home_rot, cfg.peg_in_hole)
    if name == "polishing":
        return Polishing(n, operator, home_pos, home_rot, cfg.polishing)
    if name == "guidance":
        return Guidance(n, operator, home_pos, home_rot, cfg.guidance, handle_home)
    raise ValueError(f"unknown scene {name!r}; choose from {sorted(SCENES)}")
