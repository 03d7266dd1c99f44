"""N independent MuJoCo Panda simulations stepped together; exposes B(q), h + g and sensors as float64 tensors."""

from __future__ import annotations

from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from a3cqp_rl.robot.kinematics import Kinematics
from a3cqp_rl.robot.mjcf import DEFAULT_TOOL, compose_mjcf
from a3cqp_rl.robot.specs import PANDA_HOME

__all__ = ["SimState", "PandaSim", "full_mass_matrix", "mujoco_dynamics"]


def full_mass_matrix(m: mujoco.MjModel, d: mujoco.MjData, dst: np.ndarray) -> None:
    """Write the dense joint-space inertia [nv, nv] into dst (MuJoCo >= 4: mj_fullM(m, d, dst); 3.x: (m, dst, qM))."""
    if hasattr(d, "qM"):  # MuJoCo 3.x
        mujoco.mj_fullM(m, dst, d.qM)
    else:
        mujoco.mj_fullM(m, d, dst)


_I1, _I2 = [1, 2, 0], [2, 0, 1]


def _cross(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Row-wise cross product of [N, 3] arrays (np.cross has ~10 µs of overhead per call)."""
    return a[:, _I1] * b[:, _I2] - a[:, _I2] * b[:, _I1]


def mujoco_dynamics(model: mujoco.MjModel, q: torch.Tensor, qd: torch.Tensor | None = None
                    ) -> tuple[torch.Tensor, torch.Tensor]:
    """B(q) [B, 7, 7] (kg m²) and h(q, q̇) + g(q) [B, 7] (N m) from MuJoCo for arbitrary states (float64, loop)."""
    q_np = q.detach().cpu().numpy().astype(np.float64)
    qd_np = np.zeros_like(q_np) if qd is None else qd.detach().cpu().numpy().astype(np.float64)
    d = mujoco.MjData(model)
    mass = np.zeros((len(q_np), model.nv, model.nv))
    bias = np.zeros((len(q_np), model.nv))
    for i in range(len(q_np)):
        d.qpos[:7], d.qvel[:7] = q_np[i], qd_np[i]
        mujoco.mj_fwdPosition(model, d)
        mujoco.mj_fwdVelocity(model, d)
        full_mass_matrix(model, d, mass[i])
        bias[i] = d.qfrc_bias
    return torch.from_numpy(mass[:, :7, :7]), torch.from_numpy(bias[:, :7])


@dataclass(frozen=True)
class SimState:
    """State and dynamics of N arms at the current time (tensors share memory with the simulator buffers)."""

    q: torch.Tensor
    """Joint positions [N, 7] (rad)."""
    qd: torch.Tensor
    """Joint velocities [N, 7] (rad/s)."""
    mass: torch.Tensor
    """Joint-space inertia B(q) [N, 7, 7] (kg m^2), armature included."""
    bias: torch.Tensor
    """h(q, q̇) + g(q) [N, 7] (N m): Coriolis, centrifugal and gravity torques (MuJoCo qfrc_bias)."""
    tau_ext: torch.Tensor
    """External joint torques of the previous step [N, 7] (N m): applied forces + contacts + joint-limit forces."""
    ft: torch.Tensor
    """F/T sensor reading of the previous step [N, 6] (N, N m), sensor frame: wrench the flange exerts on the
    sensor + tool subtree (includes the tool's weight)."""
    f_env: torch.Tensor
    """Environment wrench on the tool [N, 6] (N, N m about the sensor site), world frame, from the F/T reading with
    the tool's weight and the inertial force m a_com of the sensor + tool subtree removed (previous step's
    acceleration; the rotational inertia term is neglected)."""
    kin: Kinematics | None = None
    """Pose, Jacobian, J̇q̇ and twist of the control site (PandaSim.control_site) from MuJoCo's own kinematics of
    this step (mj_jacSite, mj_jacDot), world frame; pass it to A3CQPController.step(kin=...) to skip the torch FK."""


class PandaSim:
    """N Panda arms in MuJoCo (one MjModel, N MjData), split-stepped so control sees fresh B(q), h + g.

    Usage per control period: `s = sim.observe()` (mj_step1: kinematics, B, bias) -> optional `sim.push(...)` ->
    `sim.step(tau)` (mj_step2: actuation, contacts, integration).

    Args:
        n: number of arms.
        tool: tool name (see a3cqp_rl.robot.mjcf.TOOLS).
        scene: extra MJCF bodies for the worldbody (e.g. a3cqp_rl.robot.mjcf.table_xml()).
        q0: initial joint configuration [7] (rad); default the "ready" pose.
        timestep: simulation period [s] (default the MJCF's 1 ms).
        control_site: site whose kinematics `observe()` returns in `SimState.kin` (None: skip them).
    """

    def __init__(self, n: int = 1, tool: str = DEFAULT_TOOL, scene: str = "", q0: tuple[float, ...] = PANDA_HOME,
                 timestep: float | None = None, control_site: str = "tcp") -> None:
        self.model = mujoco.MjModel.from_xml_string(compose_mjcf(tool, scene))
        if timestep is not None:
            self.model.opt.timestep = timestep
        self.n = n
        self.datas = [mujoco.MjData(self.model) for _ in range(n)]
        self._mass = np.zeros((n, 7, 7))
        self._bias = np.zeros((n, 7))
        self._q = np.zeros((n, 7))
        self._qd = np.zeros((n, 7))
        self._tau_ext = np.zeros((n, 7))
        self._ft = np.zeros((n, 6))
        self._f_env = np.zeros((n, 6))
        self._ft_body = int(self.model.site_bodyid[self.model.site("ft_site").id])
        self._ft_site = self.model.site("ft_site").id
        self._tool_mass = float(self.model.body_subtreemass[self._ft_body])
        self._root_body = int(self.model.body_rootid[self._ft_body])
        self._R = np.zeros((n, 3, 3))
        self._site_pos, self._com, self._root_com = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
        self._cacc, self._cvel = np.zeros((n, 6)), np.zeros((n, 6))
        self._sensor_adr = (self.model.sensor("ft_force").adr[0], self.model.sensor("ft_torque").adr[0])
        self.site_ids = {name: self.model.site(name).id for name in ("tcp", "handle", "ft_site", "flange")}
        self._tau_push = np.zeros((n, self.model.nv))
        self._pushed = False
        self.control_site = control_site
        nv = self.model.nv
        self._cs = self.model.site(control_site).id if control_site is not None else -1
        self._jac = np.zeros((n, 6, nv))  # rows: linear (mj_jacSite jacp), angular (jacr)
        self._jac_dot = np.zeros((n, 6, nv))
        self._cs_pos, self._cs_rot = np.zeros((n, 3)), np.zeros((n, 3, 3))
        self._jdot_qdot, self._twist = np.zeros((n, 6)), np.zeros((n, 6))
        # Views into each MjData's buffers, made once: gathering them with one np.stack per field costs ~10 µs for
        # 64 arms, where per-arm slicing and copying cost ~1 µs per field and arm (most of the old observe()).
        # Whole small arrays are gathered (sensordata, site_xpos, ...) and indexed afterwards: fewer stacks.
        b, cs = self._ft_body, max(self._cs, 0)
        self._views = {name: [get(d) for d in self.datas] for name, get in (
            ("q", lambda d: d.qpos[:7]), ("qd", lambda d: d.qvel[:7]), ("bias", lambda d: d.qfrc_bias[:7]),
            ("sensordata", lambda d: d.sensordata), ("site_xpos", lambda d: d.site_xpos),
            ("site_xmat", lambda d: d.site_xmat), ("subtree_com", lambda d: d.subtree_com),
            ("cacc", lambda d: d.cacc[b]), ("cvel", lambda d: d.cvel[b]), ("cs_pos", lambda d: d.site_xpos[cs]),
            ("ctrl", lambda d: d.ctrl[:7]), ("qfrc_constraint", lambda d: d.qfrc_constraint[:7]),
            ("qfrc_applied", lambda d: d.qfrc_applied[:7]))}
        m = self.model
        self._gathered = {"sensordata": np.zeros((n, m.nsensordata)), "site_xpos": np.zeros((n, m.nsite, 3)),
                          "site_xmat": np.zeros((n, m.nsite, 9)), "subtree_com": np.zeros((n, m.nbody, 3))}
        # the per-arm arguments of the MuJoCo calls in observe()/step(), made once: at N = 64 building the views
        # (self._jac[i, :3], ...) each step cost as much as the calls themselves
        self._fullM = (lambda d, dst: mujoco.mj_fullM(m, dst, d.qM)) if hasattr(self.datas[0], "qM") else (
            lambda d, dst: mujoco.mj_fullM(m, d, dst))  # MuJoCo 3.x / >= 4 signatures (see full_mass_matrix)
        self._observe_args = [(d, self._mass[i], self._jac[i, :3], self._jac[i, 3:], self._jac_dot[i, :3],
                               self._jac_dot[i, 3:], self._views["cs_pos"][i]) for i, d in enumerate(self.datas)]
        self.reset(np.broadcast_to(np.asarray(q0, dtype=np.float64), (n, 7)))

    @property
    def dt(self) -> float:
        """Simulation (= control) period [s]."""
        return float(self.model.opt.timestep)

    @property
    def time(self) -> float:
        """Simulated time of arm 0 [s]."""
        return float(self.datas[0].time)

    def reset(self, q: np.ndarray | torch.Tensor, qd: np.ndarray | torch.Tensor | None = None,
              idx: list[int] | None = None) -> None:
        """Set joint positions [N or len(idx), 7] (rad) and velocities (rad/s, default 0) and clear forces."""
        idx = list(range(self.n)) if idx is None else list(idx)
        q = np.asarray(q, dtype=np.float64).reshape(len(idx), 7)
        qd = np.zeros_like(q) if qd is None else np.asarray(qd, dtype=np.float64).reshape(len(idx), 7)
        for k, i in enumerate(idx):
            d = self.datas[i]
            mujoco.mj_resetData(self.model, d)
            d.qpos[:7] = q[k]
            d.qvel[:7] = qd[k]
            mujoco.mj_forward(self.model, d)
            self._tau_ext[i] = 0.0
            self._ft[i] = d.sensordata[self._sensor_adr[0]:self._sensor_adr[0] + 3].tolist() + \
                d.sensordata[self._sensor_adr[1]:self._sensor_adr[1] + 3].tolist()

    def observe(self) -> SimState:
        """Run mj_step1 on every arm and return state, B(q), h + g, last-step sensors and the control site's
        kinematics as float64 tensors."""
        m, v, cs = self.model, self._views, self._cs
        cs_body = int(m.site_bodyid[cs]) if cs >= 0 else -1
        if self._pushed:  # forces of push() last only one step
            for d in self.datas:
                d.xfrc_applied[:] = 0.0
            self._tau_push[:] = 0.0
            self._pushed = False
        step1, full_m, jac_site, jac_dot = mujoco.mj_step1, self._fullM, mujoco.mj_jacSite, mujoco.mj_jacDot
        for d, mass, jacp, jacr, jdp, jdr, cs_pos in self._observe_args:
            step1(m, d)  # kinematics, B(q), h + g, sensors at the current state
            full_m(d, mass)
            if cs >= 0:
                jac_site(m, d, jacp, jacr, cs)
                jac_dot(m, d, jdp, jdr, cs_pos, cs_body)
        stack, g = np.stack, self._gathered
        for name in ("q", "qd", "bias"):
            stack(v[name], out=getattr(self, "_" + name))
        for name, buf in g.items():
            stack(v[name], out=buf)
        stack(v["cacc"], out=self._cacc)
        stack(v["cvel"], out=self._cvel)
        fa, ta = self._sensor_adr
        self._ft[:, :3] = g["sensordata"][:, fa:fa + 3]
        self._ft[:, 3:] = g["sensordata"][:, ta:ta + 3]
        self._R[:] = g["site_xmat"][:, self._ft_site].reshape(-1, 3, 3)
        self._site_pos[:] = g["site_xpos"][:, self._ft_site]
        self._com[:] = g["subtree_com"][:, self._ft_body]
        self._root_com[:] = g["subtree_com"][:, self._root_body]
        self._update_f_env()
        kin = None
        if cs >= 0:
            self._cs_pos[:] = g["site_xpos"][:, cs]
            self._cs_rot[:] = g["site_xmat"][:, cs].reshape(-1, 3, 3)
            jac, qd = self._jac[:, :, :7], self._qd[:, :, None]
            np.matmul(jac, qd, out=self._twist[:, :, None])  # ẋ = J q̇
            np.matmul(self._jac_dot[:, :, :7], qd, out=self._jdot_qdot[:, :, None])  # J̇q̇
            kin = Kinematics(pos=torch.from_numpy(self._cs_pos), rot=torch.from_numpy(self._cs_rot),
                             jac=torch.from_numpy(jac), jdot_qdot=torch.from_numpy(self._jdot_qdot),
                             twist=torch.from_numpy(self._twist))
        return SimState(q=torch.from_numpy(self._q), qd=torch.from_numpy(self._qd), mass=torch.from_numpy(self._mass),
                        bias=torch.from_numpy(self._bias), tau_ext=torch.from_numpy(self._tau_ext),
                        ft=torch.from_numpy(self._ft), f_env=torch.from_numpy(self._f_env), kin=kin)

    def _update_f_env(self) -> None:
        """Environment wrench on the tool from the F/T reading, batched over arms (see SimState.f_env).

        Newton on the sensor + tool subtree: F_env = m a_com − m g − R·reading. MuJoCo's com-based body
        acceleration cacc (rot, lin; at the tree's centre of mass c, gravity included as −g) gives the material
        acceleration of the subtree's centre of mass p as lin + α × (p − c) + ω × v_p (as mj_objectAcceleration).
        """
        r = self._com - self._root_com  # (N, 3)
        w, v = self._cvel[:, :3], self._cvel[:, 3:] + _cross(self._cvel[:, :3], r)
        a_com = self._cacc[:, 3:] + _cross(self._cacc[:, :3], r) + _cross(w, v)
        support = self._tool_mass * a_com  # weight support + m a
        flange = self._R @ self._ft.reshape(-1, 2, 3).transpose(0, 2, 1)  # (N, 3, 2): R·force, R·torque
        self._f_env[:, :3] = support - flange[:, :, 0]
        self._f_env[:, 3:] = _cross(self._com - self._site_pos, support) - flange[:, :, 1]

    def push(self, force_world: np.ndarray | torch.Tensor, site: str = "handle",
             torque_world: np.ndarray | torch.Tensor | None = None) -> None:
        """Apply a world-frame force [N, 3] (N) (and torque [N, 3], N m) at `site` during the next step()."""
        force = np.asarray(force_world, dtype=np.float64).reshape(self.n, 3)
        torque = np.zeros_like(force) if torque_world is None else np.asarray(torque_world, np.float64).reshape(-1, 3)
        sid = self.site_ids[site] if site in self.site_ids else self.model.site(site).id
        body = int(self.model.site_bodyid[sid])
        for i, d in enumerate(self.datas):
            if np.any(force[i]) or np.any(torque[i]):
                # a body force (xfrc_applied, at the body CoM) so that the F/T sensor sees pushes below it
                d.xfrc_applied[body, :3] += force[i]
                d.xfrc_applied[body, 3:] += torque[i] + np.cross(d.site_xpos[sid] - d.xipos[body], force[i])
                mujoco.mj_applyFT(self.model, d, force[i], torque[i], d.site_xpos[sid], body, self._tau_push[i])
                self._pushed = True

    def step(self, tau: torch.Tensor | np.ndarray) -> None:
        """Apply joint torques [N, 7] (N m, clipped by the motors' ranges) and run mj_step2 on every arm."""
        tau = tau.detach().cpu().numpy() if isinstance(tau, torch.Tensor) else np.asarray(tau, dtype=np.float64)
        m, step2 = self.model, mujoco.mj_step2
        for d, ctrl, t in zip(self.datas, self._views["ctrl"], tau):
            ctrl[:] = t
            step2(m, d)
        np.add(np.stack(self._views["qfrc_constraint"]), np.stack(self._views["qfrc_applied"]), out=self._tau_ext)
        if self._pushed:
            self._tau_ext += self._tau_push[:, :7]

    def site_pose(self, site: str = "tcp") -> tuple[np.ndarray, np.ndarray]:
        """World position [N, 3] (m) and rotation [N, 3, 3] of a site after the last step (kinematics of step1)."""
        sid = self.model.site(site).id
        return (np.stack([d.site_xpos[sid] for d in self.datas]),
                np.stack([d.site_xmat[sid].reshape(3, 3) for d in self.datas]))

    def contact_force(self, geom: str) -> np.ndarray:
        """World-frame force [N, 3] (N) that all contacts involving `geom` exert on `geom`."""
        gid = self.model.geom(geom).id
        out = np.zeros((self.n, 3))
        f6 = np.zeros(6)
        for i, d in enumerate(self.datas):
            for c in range(d.ncon):
                con = d.contact[c]
                if gid not in (con.geom1, con.geom2):
                    continue
                mujoco.mj_contactForce(self.model, d, c, f6)
                f_world = con.frame.reshape(3, 3).T @ f6[:3]  # force on geom2 from geom1, in world
                out[i] += -f_world if con.geom1 == gid else f_world  # the frame's normal points from geom1 to geom2
        return out
