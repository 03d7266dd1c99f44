"""N independent MuJoCo Panda simulations stepped together; exposes B(q), h + g and sensors as float64 tensors."""

from __future__ import annotations

import weakref
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass

import mujoco
import numpy as np
import torch

from a3cqp_rl.robot import contact_filter, sense
from a3cqp_rl.robot.kinematics import Kinematics
from a3cqp_rl.robot.mjcf import DEFAULT_TOOL, compose_mjcf
from a3cqp_rl.robot.specs import PANDA_HOME

__all__ = ["SimState", "PandaSim", "ShardedPandaSim", "cross3", "full_mass_matrix", "mujoco_dynamics", "grid_origins"]


def full_mass_matrix(m: mujoco.MjModel, d: mujoco.MjData, dst: np.ndarray) -> None:
    """Write the dense joint-space inertia [nv, nv] into dst (MuJoCo >= 4: mj_fullM(m, d, dst); 3.x: (m, dst, qM))."""
    if hasattr(d, "qM"):  # MuJoCo 3.x
        mujoco.mj_fullM(m, dst, d.qM)
    else:
        mujoco.mj_fullM(m, d, dst)


_I1, _I2 = np.array([1, 2, 0], dtype=np.intp), np.array([2, 0, 1], dtype=np.intp)


def cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Cross product over the last axis of [..., 3] arrays, broadcast (np.cross has ~10 µs of overhead per call;
    `take` with index arrays is ~3x faster than indexing with lists, the same products)."""
    return a.take(_I1, axis=-1) * b.take(_I2, axis=-1) - a.take(_I2, axis=-1) * b.take(_I1, axis=-1)


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
    this step (from cdof, cdof_dot: what mj_jacSite, mj_jacDot give), world frame; pass it to
    A3CQPController.step(kin=...) to skip the torch FK."""


def _grid(text: str, n: int) -> np.ndarray:
    """Origins [n, 3] of n copies of the MJCF `text` on a square grid around the world origin (small coordinates,
    small round-off), far enough apart that no copy can touch another."""
    spacing = 2.0 * _reach(mujoco.MjModel.from_xml_string(text)) + 1.0
    side = int(np.ceil(np.sqrt(n)))
    return np.array([[spacing * (i % side - (side - 1) / 2), spacing * (i // side - (side - 1) / 2), 0.0]
                     for i in range(n)])


def grid_origins(tool: str, scene: str, n: int) -> np.ndarray:
    """Where PandaSim(n, tool, scene) places its arms' copies [n, 3] (m): pick rows of it as a smaller batch's
    `origins` to compute with the same coordinates, hence the same round-off, as in the batch of n."""
    return _grid(compose_mjcf(tool, scene), n)


def _arm_rows(a: np.ndarray | torch.Tensor, rows: int, name: str, unit: str) -> np.ndarray:
    """`a` as float64 [rows, 7] (one arm may give [7]); a wrong shape or a non-finite value raises ValueError naming
    the arms. Why: MuJoCo zeroes every arm's controls for one bad one, and resets the whole model for a bad qpos."""
    a = a.detach().cpu().numpy() if isinstance(a, torch.Tensor) else np.asarray(a, dtype=np.float64)
    if a.shape != (rows, 7) and not (rows == 1 and a.shape == (7,)):
        raise ValueError(f"{name} must have shape ({rows}, 7) ({unit}), got {a.shape}")
    a = a.reshape(rows, 7)
    ok = np.isfinite(a).all(axis=1)
    if not ok.all():
        raise ValueError(f"{name} is not finite for arms (rows) {np.flatnonzero(~ok)[:10].tolist()}")
    return a.astype(np.float64, copy=False)


def _replicate(text: str, n: int, origins: np.ndarray | None = None) -> tuple[mujoco.MjModel, list[str], np.ndarray]:
    """One model holding n copies of the MJCF `text` (arm, tool and scene), prefixed "arm{i}/" and placed at
    `origins` [n, 3] (default `_grid(text, n)`) (returns the model, the prefixes and the copies' origins)."""
    child = mujoco.MjSpec.from_string(text)
    for key in list(child.keys):  # keyframes are per-copy qpos vectors: not valid in the composite
        child.delete(key)
    origins = _grid(text, n) if origins is None else np.asarray(origins, dtype=np.float64).reshape(n, 3)
    parent = mujoco.MjSpec()
    parent.copy_during_attach = True  # attach the same child n times
    for name in [a for a in dir(child.option) if not a.startswith("_")]:
        setattr(parent.option, name, getattr(child.option, name))
    for name in ("degree", "autolimits", "eulerseq"):
        setattr(parent.compiler, name, getattr(child.compiler, name))
    prefixes = [f"arm{i}/" for i in range(n)]
    for prefix, pos in zip(prefixes, origins):
        parent.attach(child, prefix=prefix, frame=parent.worldbody.add_frame(pos=pos))
    return parent.compile(), prefixes, origins


def _reach(m: mujoco.MjModel) -> float:
    """Horizontal radius about the world origin that bounds every geom of the model in any pose: static geoms
    where they are, moving ones by the length of their body chain."""
    d = mujoco.MjData(m)
    mujoco.mj_forward(m, d)
    reach = 0.0
    for g in range(m.ngeom):
        if int(m.geom_type[g]) in (int(mujoco.mjtGeom.mjGEOM_PLANE), int(mujoco.mjtGeom.mjGEOM_HFIELD)):
            raise ValueError("PandaSim(n > 1) simulates all arms in one MuJoCo model: the scene needs finite geoms "
                             "(no planes or height fields, which would reach the other arms)")
        b = int(m.geom_bodyid[g])
        if m.body_weldid[b] == 0:  # static
            r = float(np.linalg.norm(d.geom_xpos[g, :2]))
        else:
            r = float(np.linalg.norm(m.geom_pos[g]))
            while b:
                r += float(np.linalg.norm(m.body_pos[b]))
                b = int(m.body_parentid[b])
        reach = max(reach, r + float(m.geom_rbound[g] + m.geom_margin[g]))
    return reach


def _can_collide(m: mujoco.MjModel) -> bool:
    """Whether any two geoms of different bodies pass MuJoCo's contype/conaffinity filter (or explicit pairs exist);
    the arm alone never collides with itself (contype 2, conaffinity 1), so without a scene there are no contacts."""
    if m.npair:
        return True
    ct, ca = m.geom_contype.astype(np.int64), m.geom_conaffinity.astype(np.int64)
    compatible = ((ct[:, None] & ca[None, :]) | (ca[:, None] & ct[None, :])) != 0
    return bool((compatible & (m.geom_bodyid[:, None] != m.geom_bodyid[None, :])).any())


_OUTPUTS = {"_q": (7,), "_qd": (7,), "_mass": (7, 7), "_bias": (7,), "_tau_ext": (7,), "_ft": (6,), "_f_env": (6,),
            "_cs_pos": (3,), "_cs_rot": (3, 3), "_jt": (7, 12), "_jdot_qdot": (6,), "_twist": (6,)}
"""Per-arm shapes of the arrays behind SimState (`_jt` = [Jᵀ | J̇ᵀ] of the control site, see `_site_kinematics`)."""


def _output_buffers(n: int) -> dict[str, np.ndarray]:
    """Zeroed arrays [n, ...] for the outputs of PandaSim.observe (see `_OUTPUTS`)."""
    return {name: np.zeros((n, *shape)) for name, shape in _OUTPUTS.items()}


def _sim_state(sim: PandaSim | ShardedPandaSim, kin: bool) -> SimState:
    """SimState of the arrays `sim` holds (tensors sharing their memory), with the control site's kinematics: made
    once per sim, as the arrays are written in place (a copy of the sim, with arrays of its own, makes its own)."""
    cached = sim.__dict__.get("_state")
    if cached is not None and cached[0] == id(sim):
        return cached[1]
    t = torch.from_numpy
    k = None
    if kin:
        k = Kinematics(pos=t(sim._cs_pos), rot=t(sim._cs_rot), jac=t(sim._jt[:, :, :6].transpose(0, 2, 1)),
                       jdot_qdot=t(sim._jdot_qdot), twist=t(sim._twist))
    state = SimState(q=t(sim._q), qd=t(sim._qd), mass=t(sim._mass), bias=t(sim._bias), tau_ext=t(sim._tau_ext),
                     ft=t(sim._ft), f_env=t(sim._f_env), kin=k)
    sim._state = (id(sim), state)  # (~20 µs a control period: ten tensors and two dataclasses)
    return state


class PandaSim:
    """N Panda arms in MuJoCo, split-stepped so control sees fresh B(q), h + g.

    Usage per control period: `s = sim.observe()` (mj_step1: kinematics, B, bias) -> optional `sim.push(...)` ->
    `sim.step(tau)` (mj_step2: actuation, contacts, integration).

    All N arms live in ONE MjModel/MjData (N > 1: N prefixed copies "arm{i}/" of arm + tool + scene on a grid, far
    enough apart never to touch), so a control period is one mj_step1 and one mj_step2 call, and everything per arm
    (state, B(q) blocks of the sparse M, h + g, sensors, site poses, Jacobian and J̇ from cdof / cdof_dot, pushes)
    is read and written with index arrays made once in __init__. Why: with one MjData per arm (the previous design)
    N = 64 arms cost ~2.5-4 ms per step, of which MuJoCo's own C calls were only ~11 µs per arm (~0.7 ms); the rest
    was the Python loop over the MjData and gathering their buffers. With one MjData: ~0.75 ms (bench/controller.py,
    N = 64, 2 loaded cores), about 2/3 of it mj_step1 + mj_step2. The arms stay independent: no contacts between
    copies, and MuJoCo's constraint islands keep each arm's constraint problem separate, so every arm follows the
    single-arm simulation to round-off (tests/test_sim_batched.py checks it against separate single-arm models; in
    sliding contact of a cylinder, whose collider is iterative, round-off grows as it does in one arm run twice).

    Args:
        n: number of arms.
        tool: tool name (see a3cqp_rl.robot.mjcf.TOOLS).
        scene: extra MJCF bodies for the worldbody (e.g. a3cqp_rl.robot.mjcf.table_xml()); with n > 1 its geoms
            must be finite (no planes) and free bodies in it must stay near their arm.
        q0: initial joint configuration [7] (rad); default the "ready" pose.
        timestep: simulation period [s] (default the MJCF's 1 ms).
        control_site: site whose kinematics `observe()` returns in `SimState.kin` (None: skip them).
        origins: where the arms' copies sit in the composite's world [n, 3] (m); default a grid around the origin
            (n = 1: the bare model). ShardedPandaSim gives each of its parts the places its arms have in the grid
            of all N, so that every arm computes with the same coordinates, hence the same round-off, either way.
        buffers: arrays [n, ...] to write the outputs of `observe()` into (ShardedPandaSim: views of its own);
            default new ones (see `_output_buffers`).
        warmstart: start MuJoCo's constraint solver from the previous step's accelerations where that is cheaper
            (MuJoCo's default). Off by default: MuJoCo makes that choice once for the whole model, by the summed
            cost of every arm's constraints, so with it an arm's contact solve depended on which other arms shared
            its model (another batch, `--workers`, `--threads`: other numbers in contact at round-off, which the
            contact's chaos grew into other trial outcomes). Without it, and with the sparse constraint Jacobian
            (below), every arm's solve starts from its own unconstrained accelerations and runs on its own
            constraint island: a batch split into models (ShardedPandaSim) computes the same numbers bit for bit
            (tests/test_sim_batched.py). Batches of other sizes can still differ at round-off, where MuJoCo's
            solver stops at another iteration (docs/panda.md).
        contact_prefilter: drop, before MuJoCo's narrow phase, the pairs of the tool's collision mesh and the scene's
            static boxes that a plane keeps apart (a3cqp_rl.robot.contact_filter: exact, the same contacts and
            numbers bit for bit; the peg's 32 bore boxes are most of the collision time in contact). Default on.
    """

    def __init__(self, n: int = 1, tool: str = DEFAULT_TOOL, scene: str = "", q0: tuple[float, ...] = PANDA_HOME,
                 timestep: float | None = None, control_site: str = "tcp", origins: np.ndarray | None = None,
                 buffers: dict[str, np.ndarray] | None = None, warmstart: bool = False,
                 contact_prefilter: bool = True) -> None:
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 1:
            raise ValueError(f"n (the number of arms) must be an integer >= 1, got {n!r}")
        text = compose_mjcf(tool, scene)
        m1 = mujoco.MjModel.from_xml_string(text)
        # positions of arm i are reported in its own copy's frame: composite world minus self._origin[i]
        self.model, self._prefixes, self._origin = ((m1, [""], np.zeros((1, 3))) if n == 1 and origins is None
                                                    else _replicate(text, n, origins))
        if timestep is not None:
            self.model.opt.timestep = timestep
        # one arm's bad state must not make MuJoCo reset every arm of the model (its default on a bad qpos or qacc)
        self.model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_AUTORESET)
        if not warmstart:
            self.model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)
        # MuJoCo's default picks the dense Jacobian below 60 dofs (fewer than 9 arms), and its dense solver does not
        # keep the arms' constraint islands apart: the same arm then solved differently next to other arms in contact
        self.model.opt.jacobian = int(mujoco.mjtJacobian.mjJAC_SPARSE)
        if not _can_collide(m1):  # e.g. no scene: skip the collision pass (~1/3 of mj_step1 at N = 64), same physics
            self.model.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_CONTACT)
        self.n = n
        self.data = mujoco.MjData(self.model)
        m = self.model
        self._contact_filter = self._attach_contact_filter() if contact_prefilter else None
        # --- which element of the composite belongs to which arm (copies are contiguous in body order)
        nb1 = m1.nbody - 1
        body_arm = np.concatenate([[-1], np.arange(m.nbody - 1) // nb1])
        for i, p in enumerate(self._prefixes):
            assert body_arm[m.body(p + "link0").id] == i, "attached copies are not contiguous"
        jnt_arm = body_arm[m.jnt_bodyid]
        self._geom_arm = body_arm[m.geom_bodyid]
        self._contype, self._conaffinity = m.geom_contype.copy(), m.geom_conaffinity.copy()  # park() / reset()
        qsize = {int(mujoco.mjtJoint.mjJNT_FREE): (7, 6), int(mujoco.mjtJoint.mjJNT_BALL): (4, 3)}
        self._arm_qpos, self._arm_dof, self._arm_bodies, self._arm_act, self._arm_mocap = [], [], [], [], []
        for i in range(n):
            jnts = np.flatnonzero(jnt_arm == i)
            sizes = [qsize.get(int(m.jnt_type[j]), (1, 1)) for j in jnts]
            self._arm_qpos.append(np.concatenate([np.arange(m.jnt_qposadr[j], m.jnt_qposadr[j] + s[0])
                                                  for j, s in zip(jnts, sizes)]).astype(np.intp))
            self._arm_dof.append(np.concatenate([np.arange(m.jnt_dofadr[j], m.jnt_dofadr[j] + s[1])
                                                 for j, s in zip(jnts, sizes)]).astype(np.intp))
            bodies = np.flatnonzero(body_arm == i)
            self._arm_bodies.append(bodies)
            self._arm_mocap.append(bodies[m.body_mocapid[bodies] >= 0])
            self._arm_act.append(np.arange(i * m1.nu, (i + 1) * m1.nu))
        self._arm_sensordata = [np.arange(i * m1.nsensordata, (i + 1) * m1.nsensordata) for i in range(n)]
        # --- per-arm index arrays [N, ...] into the MjData buffers
        joints = np.array([[m.joint(f"{p}joint{k}").id for k in range(1, 8)] for p in self._prefixes])
        self._qadr, self._dadr = m.jnt_qposadr[joints].astype(np.intp), m.jnt_dofadr[joints].astype(np.intp)
        act_of_joint = {int(m.actuator_trnid[a, 0]): a for a in range(m.nu)
                        if m.actuator_trntype[a] == mujoco.mjtTrn.mjTRN_JOINT}
        self._act = np.array([[act_of_joint[int(j)] for j in row] for row in joints], dtype=np.intp)
        self._m_idx = self._mass_indices(m, self._dadr)
        self._ft_site = self._site_index("ft_site")
        self._ft_body = m.site_bodyid[self._ft_site].astype(np.intp)
        self._root_body = m.body_rootid[self._ft_body].astype(np.intp)
        self._tool_mass = float(m1.body_subtreemass[m1.site_bodyid[m1.site("ft_site").id]])
        fa, ta = (np.array([m.sensor(p + name).adr[0] for p in self._prefixes]) for name in ("ft_force", "ft_torque"))
        self._ft_adr = np.concatenate([fa[:, None] + np.arange(3), ta[:, None] + np.arange(3)], axis=1)
        # ids in self.model of arm 0's named sites (those of arm i: self._site_index(name)[i])
        self.site_ids = {name: int(self._site_index(name)[0]) for name in ("tcp", "handle", "ft_site", "flange")}
        self._t0 = np.zeros(n)  # data.time at each arm's last reset
        # --- output buffers (the tensors of SimState share their memory) and scratch
        for name, buf in (_output_buffers(n) if buffers is None else buffers).items():
            if buf.shape != (n, *_OUTPUTS[name]):
                raise ValueError(f"buffers[{name!r}] has shape {buf.shape}, expected {(n, *_OUTPUTS[name])}")
            setattr(self, name, buf)
        self._tau_push = np.zeros((n, 7))
        self._R = np.zeros((n, 3, 3))
        self._site_pos, self._com, self._root_com = np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3))
        self._cacc, self._cvel = np.zeros((n, 6)), np.zeros((n, 6))
        self._pushed = False
        self.control_site = control_site
        self._cs = self._site_index(control_site) if control_site is not None else None
        if self._cs is not None:
            self._cs_body = m.site_bodyid[self._cs].astype(np.intp)
            self._cs_mask = self._ancestor_mask(self._cs_body[0])
        # [Jᵀ | J̇ᵀ] [N, 7, 12] of the control site (rows: dofs; columns: linear, angular) and what makes it
        self._dd, self._vel = np.zeros((n, 7, 12)), np.zeros((n, 12))
        self._w = np.zeros((n, 12, 12))
        for blk in (0, 6):
            self._w[:, blk + 3:blk + 6, blk:blk + 3] = self._w[:, blk:blk + 3, blk + 3:blk + 6] = np.eye(3)
        # flat positions in w of the skew entries [r]ₓ (blocks (0, 0) and (6, 6)) and [v_p]ₓ (block (0, 6)):
        # + entries (1,0)=z (2,1)=x (0,2)=y, − entries (0,1)=z (1,2)=x (2,0)=y
        plus, minus = [(1, 0), (2, 1), (0, 2)], [(0, 1), (1, 2), (2, 0)]
        self._skew_idx = np.array([12 * (r0 + i) + c0 + j for r0, c0 in ((0, 0), (6, 6), (0, 6))
                                   for i, j in plus + minus], dtype=np.intp)
        self._skew_src = np.array([2, 0, 1, 5, 3, 4, 8, 6, 7, 11, 9, 10], dtype=np.intp)
        self._site_cache: dict[str, tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray | None]] = {}
        # park(): MuJoCo's sleeping skips a parked arm's dynamics; no tree sleeps on its own (policy "never")
        self._arm_tree = m.body_treeid[[m.body(p + "link1").id for p in self._prefixes]].astype(np.intp)
        self._body_arm = body_arm
        self._body_contype, self._body_conaffinity = m.body_contype.copy(), m.body_conaffinity.copy()
        self._body_pos0 = m.body_pos.copy()  # where the MJCF put each body (move_static_body)
        m.opt.enableflags |= int(mujoco.mjtEnableBit.mjENBL_SLEEP)
        m.tree_sleep_policy[:] = int(mujoco.mjtSleepPolicy.mjSLEEP_NEVER)
        self._native_observe = sense.observer(self)  # None: the numpy read-out below
        self.reset(np.broadcast_to(np.asarray(q0, dtype=np.float64), (n, 7)))

    @staticmethod
    def _mass_indices(m: mujoco.MjModel, dofs: np.ndarray) -> np.ndarray:
        """Indices [N, 7, 7] of each arm's B(q) block in MuJoCo's sparse lower-triangular M (CSR: M_rowadr,
        M_rownnz, M_colind); one np.take replaces mj_fullM of the whole (N·nv)² matrix."""
        idx = np.zeros(dofs.shape + (7,), dtype=np.intp)
        for i, arm in enumerate(dofs):
            for r, row in enumerate(arm):
                start = m.M_rowadr[row]
                cols = list(m.M_colind[start:start + m.M_rownnz[row]])
                for c in range(r + 1):
                    idx[i, r, c] = idx[i, c, r] = start + cols.index(arm[c])
        return idx

    def _site_index(self, site: str) -> np.ndarray:
        """Global ids [N] of the site `site` of every arm."""
        return np.array([self.model.site(p + site).id for p in self._prefixes], dtype=np.intp)

    def _ancestor_mask(self, body: int) -> np.ndarray | None:
        """[7] 1.0 for the arm joints that move `body`, 0.0 for the others (None: all move it)."""
        chain, b = set(), int(body)
        while b:
            chain.update(range(self.model.body_dofadr[b], self.model.body_dofadr[b] + self.model.body_dofnum[b]))
            b = int(self.model.body_parentid[b])
        mask = np.array([float(dof in chain) for dof in self._dadr[0]])
        return None if mask.all() else mask

    @property
    def dt(self) -> float:
        """Simulation (= control) period [s]."""
        return float(self.model.opt.timestep)

    @property
    def time(self) -> float:
        """Simulated time of arm 0 [s] (since its last reset)."""
        return float(self.data.time - self._t0[0])

    def reset(self, q: np.ndarray | torch.Tensor, qd: np.ndarray | torch.Tensor | None = None,
              idx: list[int] | None = None) -> None:
        """Set joint positions [N or len(idx), 7] (rad) and velocities (rad/s, default 0) and clear forces."""
        m, d = self.model, self.data
        arms = np.arange(self.n) if idx is None else np.asarray(list(idx), dtype=np.intp).reshape(-1)
        q = _arm_rows(q, len(arms), "q", "rad")
        qd = np.zeros_like(q) if qd is None else _arm_rows(qd, len(arms), "qd", "rad/s")
        g = np.flatnonzero(np.isin(self._geom_arm, arms))  # a parked arm collides again
        m.geom_contype[g], m.geom_conaffinity[g] = self._contype[g], self._conaffinity[g]
        b = np.flatnonzero(np.isin(self._body_arm, arms))
        m.body_contype[b], m.body_conaffinity[b] = self._body_contype[b], self._body_conaffinity[b]
        m.tree_sleep_policy[self._arm_tree[arms]] = int(mujoco.mjtSleepPolicy.mjSLEEP_NEVER)  # mj_forward wakes it
        partial = len(np.unique(arms)) < self.n
        if not partial:
            mujoco.mj_resetData(m, d)
            self._t0[:] = 0.0
        else:  # mj_resetData for the copies in `arms` only
            cat = lambda parts: np.concatenate([parts[i] for i in arms])  # noqa: E731
            qpos, dof, bodies, mocap = cat(self._arm_qpos), cat(self._arm_dof), cat(self._arm_bodies), cat(self._arm_mocap)
            d.qpos[qpos] = m.qpos0[qpos]
            for buf in (d.qvel, d.qacc_warmstart, d.qfrc_applied):
                buf[dof] = 0.0
            d.ctrl[cat(self._arm_act)] = 0.0
            d.xfrc_applied[bodies] = 0.0
            if len(mocap):
                d.mocap_pos[m.body_mocapid[mocap]] = m.body_pos[mocap]
                d.mocap_quat[m.body_mocapid[mocap]] = m.body_quat[mocap]
            self._t0[arms] = d.time
            others = np.setdiff1d(np.arange(self.n), arms)
            keep_s = np.concatenate([self._arm_sensordata[i] for i in others])
            saved = d.sensordata[keep_s].copy(), d.cacc[self._ft_body[others]].copy()
        d.qpos[self._qadr[arms]] = q
        d.qvel[self._dadr[arms]] = qd
        mujoco.mj_forward(m, d)
        if partial:  # the other arms keep their previous-step acceleration-stage readings
            d.sensordata[keep_s], d.cacc[self._ft_body[others]] = saved
        self._tau_ext[arms] = 0.0
        self._ft[arms] = d.sensordata[self._ft_adr[arms]]

    def _attach_contact_filter(self) -> contact_filter.Registration | None:
        """Register this model with the exact tool-box contact pre-filter (a3cqp_rl.robot.contact_filter): the
        tool's collision meshes against the scene's static boxes. None: nothing filtered."""
        m = self.model
        if m.opt.disableflags & int(mujoco.mjtDisableBit.mjDSBL_CONTACT):
            return None
        collides = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
        tool_bodies = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, p + "tool") for p in self._prefixes]
        tools = np.flatnonzero(collides & np.isin(m.geom_bodyid, tool_bodies)
                               & (m.geom_type == int(mujoco.mjtGeom.mjGEOM_MESH)))
        boxes = np.flatnonzero(collides & (m.body_weldid[m.geom_bodyid] == 0)
                               & (m.geom_type == int(mujoco.mjtGeom.mjGEOM_BOX)))
        return contact_filter.attach(m, self.data, tools, boxes)  # detached when collected with this sim

    def contact_filter_counts(self) -> tuple[int, int]:
        """(tool-box pairs MuJoCo's broad phase passed, pairs the exact pre-filter dropped) so far; (0, 0) without
        it (`contact_prefilter=False`, no tool mesh or box, or the library not built)."""
        return (0, 0) if self._contact_filter is None else self._contact_filter.counts()

    @property
    def contact_prefilter(self) -> bool:
        """Whether this model runs the exact contact pre-filter (asked for, a tool mesh and a box, library built)."""
        return self._contact_filter is not None

    def park(self, idx: list[int] | np.ndarray) -> None:
        """Set arms `idx` aside until their next reset: their collisions off (geoms' and bodies' contype and
        conaffinity: out of the broad phase too) and their velocity zeroed; MuJoCo puts an arm to sleep at the end
        of the first step it ends at rest (at once when held by h + g, as `A3CQPController.step`'s `active` does).
        A sleeping arm is frozen until its reset (torques and pushes no longer move it), costs MuJoCo nothing, and
        its read-out is skipped (its arrays keep the values of its last one).

        For an arm whose episode is over while the batch runs on: one that rests in contact (a peg left in its
        bore) would cost MuJoCo's collision and constraint solver at every step, for nothing. Its own motion is
        no longer meaningful; the other arms compute the same numbers bit for bit (MuJoCo solves each arm's
        constraints on their own, `warmstart`)."""
        idx = np.asarray(idx, dtype=np.intp).reshape(-1)
        m, d = self.model, self.data
        g = np.flatnonzero(np.isin(self._geom_arm, idx))
        m.geom_contype[g] = 0
        m.geom_conaffinity[g] = 0
        b = np.flatnonzero(np.isin(self._body_arm, idx))  # out of the broad phase too (bodies' own bitmasks)
        m.body_contype[b] = m.body_conaffinity[b] = 0
        # at rest and marked ready, the arm sleeps at the end of this step (MuJoCo then skips its dynamics) as long
        # as nothing moves it: the caller holds it with h + g (A3CQPController.step's `active`)
        if len(idx):
            d.qvel[np.concatenate([self._arm_dof[i] for i in idx])] = 0.0
        t = self._arm_tree[idx]
        m.tree_sleep_policy[t] = int(mujoco.mjtSleepPolicy.mjSLEEP_ALLOWED)
        d.tree_asleep[t] = np.where(d.tree_asleep[t] < 0, -1, d.tree_asleep[t])

    def observe(self) -> SimState:
        """Run mj_step1 (all arms) and return state, B(q), h + g, last-step sensors and the control site's
        kinematics as float64 tensors."""
        self._observe_arrays()
        return _sim_state(self, self._cs is not None)

    def _observe_arrays(self) -> None:
        """mj_step1 and the outputs of `observe` into this sim's arrays."""
        m, d, take = self.model, self.data, np.take
        if self._pushed:  # forces of push() last only one step
            d.xfrc_applied[:] = 0.0
            self._tau_push[:] = 0.0
            self._pushed = False
        mujoco.mj_step1(m, d)  # kinematics, M, h + g, position/velocity sensors at the current state
        native = self._native_observe
        if native is not None:  # the same read-out in C (a3cqp_rl/robot/sense.py)
            if native.owner() is not self:  # this sim is a copy: the call holds the original's addresses
                native = self._native_observe = sense.observer(self)
            native()
            return
        take(d.qpos, self._qadr, out=self._q)
        take(d.qvel, self._dadr, out=self._qd)
        take(d.qfrc_bias, self._dadr, out=self._bias)
        take(d.M, self._m_idx, out=self._mass)
        take(d.sensordata, self._ft_adr, out=self._ft)  # force/torque: acceleration stage, previous step
        take(d.site_xmat, self._ft_site, axis=0, out=self._R.reshape(self.n, 9))
        take(d.site_xpos, self._ft_site, axis=0, out=self._site_pos)
        take(d.subtree_com, self._ft_body, axis=0, out=self._com)
        take(d.subtree_com, self._root_body, axis=0, out=self._root_com)
        take(d.cacc, self._ft_body, axis=0, out=self._cacc)
        take(d.cvel, self._ft_body, axis=0, out=self._cvel)
        self._update_f_env()
        if self._cs is not None:
            self._site_kinematics()

    def _site_kinematics(self) -> None:
        """Pose, Jacobian J, J̇, ẋ = J q̇ and J̇q̇ of the control site for all arms at once, from MuJoCo's com-based
        dof motions d_j = cdof[j] = (ω_j; v_j) and ḋ_j = cdof_dot[j] (what mj_jacSite and mj_jacDot do per arm):
        column j of J is (v_j + ω_j × r; ω_j) with r = p − c (c: subtree com of the arm's root), of J̇
        (v̇_j + ω̇_j × r + ω_j × v_p; ω̇_j) with v_p the site's velocity. With a × r = a [r]ₓ (row vectors) that is
        one matmul [d | ḋ] @ W per arm: [Jᵀ | J̇ᵀ] (7 × 12), W = [[T(r), U(v_p)], [0, T(r)]],
        T(r) = [[[r]ₓ, I], [I, 0]], U(v) = [[[v]ₓ, 0], [0, 0]]; then q̇ᵀ [Jᵀ | J̇ᵀ] = [ẋ | J̇q̇]."""
        d, take, w = self.data, np.take, self._w
        take(d.site_xpos, self._cs, axis=0, out=self._cs_pos)
        take(d.site_xmat, self._cs, axis=0, out=self._cs_rot.reshape(self.n, 9))
        r = self._cs_pos - self._root_com
        self._cs_pos -= self._origin
        w.reshape(self.n, 144)[:, self._skew_idx[:12]] = np.concatenate([r, -r, r, -r], axis=1)[:, self._skew_src]
        v = d.cvel[self._cs_body][:, None, :] @ w[:, :6, :3]  # (ω; v_body) @ ([r]ₓ; I) = v + ω × r
        w.reshape(self.n, 144)[:, self._skew_idx[12:]] = np.concatenate([v[:, 0], -v[:, 0]], axis=1)[:, self._skew_src[:6]]
        self._dd[:, :, :6] = d.cdof[self._dadr]
        self._dd[:, :, 6:] = d.cdof_dot[self._dadr]
        np.matmul(self._dd, w, out=self._jt)
        if self._cs_mask is not None:
            self._jt *= self._cs_mask[:, None]
        np.matmul(self._qd[:, None, :], self._jt, out=self._vel[:, None, :])
        self._twist[:] = self._vel[:, :6]
        self._jdot_qdot[:] = self._vel[:, 6:]

    def _update_f_env(self) -> None:
        """Environment wrench on the tool from the F/T reading, batched over arms (see SimState.f_env).

        Newton on the sensor + tool subtree: F_env = m a_com − m g − R·reading. MuJoCo's com-based body
        acceleration cacc (rot, lin; at the tree's centre of mass c, gravity included as −g) gives the material
        acceleration of the subtree's centre of mass p as lin + α × (p − c) + ω × v_p (as mj_objectAcceleration).
        """
        r = self._com - self._root_com  # (N, 3)
        w, v = self._cvel[:, :3], self._cvel[:, 3:] + cross3(self._cvel[:, :3], r)
        a_com = self._cacc[:, 3:] + cross3(self._cacc[:, :3], r) + cross3(w, v)
        support = self._tool_mass * a_com  # weight support + m a
        flange = self._R @ self._ft.reshape(-1, 2, 3).transpose(0, 2, 1)  # (N, 3, 2): R·force, R·torque
        self._f_env[:, :3] = support - flange[:, :, 0]
        self._f_env[:, 3:] = cross3(self._com - self._site_pos, support) - flange[:, :, 1]

    def push(self, force_world: np.ndarray | torch.Tensor, site: str = "handle",
             torque_world: np.ndarray | torch.Tensor | None = None) -> None:
        """Apply a world-frame force [N, 3] (N) (and torque [N, 3], N m) at `site` during the next step()."""
        force = np.asarray(force_world, dtype=np.float64).reshape(self.n, 3)
        torque = np.zeros_like(force) if torque_world is None else np.asarray(torque_world, np.float64).reshape(-1, 3)
        arms = np.flatnonzero(np.any(force != 0, axis=1) | np.any(torque != 0, axis=1))
        if not len(arms):
            return
        force, torque = force[arms], torque[arms]  # (the arms pushed only: a few of a batch at a time)
        d = self.data
        if site not in self._site_cache:  # (a name lookup per arm costs ~1 µs: once per site, not per push)
            sid = self._site_index(site)
            body = self.model.site_bodyid[sid]
            self._site_cache[site] = sid, body, self.model.body_rootid[body], self._ancestor_mask(body[0])
        sid, body, root, mask = self._site_cache[site]
        sid, body, root = sid[arms], body[arms], root[arms]
        p = d.site_xpos[sid]
        # a body force (xfrc_applied, at the body CoM) so that the F/T sensor sees pushes below it
        d.xfrc_applied[body, :3] += force
        d.xfrc_applied[body, 3:] += torque + cross3(p - d.xipos[body], force)
        # its joint torques Jᵀ(f; τ) at p (as mj_applyFT), for tau_ext: cdof_lin·f + cdof_ang·(r × f + τ)
        cdof = d.cdof[self._dadr[arms]]
        moment = cross3(p - d.subtree_com[root], force) + torque
        tau = np.einsum("nkj,nj->nk", cdof[:, :, 3:], force) + np.einsum("nkj,nj->nk", cdof[:, :, :3], moment)
        self._tau_push[arms] += tau if mask is None else tau * mask
        self._pushed = True

    def step(self, tau: torch.Tensor | np.ndarray) -> None:
        """Apply joint torques [N, 7] (N m, clipped by the motors' ranges) and run mj_step2 (all arms)."""
        tau = _arm_rows(tau, self.n, "tau", "N m")
        d = self.data
        d.ctrl[self._act] = tau
        mujoco.mj_step2(self.model, d)
        np.add(d.qfrc_constraint[self._dadr], d.qfrc_applied[self._dadr], out=self._tau_ext)
        if self._pushed:
            self._tau_ext += self._tau_push

    @property
    def models(self) -> list[mujoco.MjModel]:
        """The MuJoCo models simulating the arms (one here; ShardedPandaSim: one per part)."""
        return [self.model]

    @property
    def ncon(self) -> int:
        """Number of MuJoCo contacts (all arms) found by the last mj_step1."""
        return int(self.data.ncon)

    def move_static_body(self, name: str, idx: list[int] | np.ndarray, offset: np.ndarray) -> None:
        """Place arms `idx`' copies of the scene's static body `name` at `offset` [len(idx), 3] (m, world) from
        where the MJCF put it (zeros: back there), e.g. a trial's plate at a height the controller does not know.
        The next step's kinematics and collision see it; nothing else of the model changes. Call it where the
        kinematics are current (after `reset`, as PandaEnv does): it runs one kinematics pass of the whole model."""
        m = self.model
        arms = np.asarray(idx, dtype=np.intp).reshape(-1)
        offset = np.asarray(offset, dtype=np.float64).reshape(len(arms), 3)
        ids = np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, self._prefixes[i] + name) for i in arms],
                       dtype=np.intp)
        if (ids < 0).any() or (m.body_weldid[ids] != 0).any() or (m.body_mocapid[ids] >= 0).any():
            raise ValueError(f"move_static_body: the scene has no static body {name!r} (one welded to the world)")
        m.body_pos[ids] = self._body_pos0[ids] + offset
        # with sleeping on, MuJoCo's kinematics computes static bodies once and skips them after: one pass with it
        # off places them (the other bodies get the same values again: qpos has not changed since the last pass)
        flags = m.opt.enableflags
        m.opt.enableflags = flags & ~int(mujoco.mjtEnableBit.mjENBL_SLEEP)
        try:
            mujoco.mj_kinematics(m, self.data)
        finally:
            m.opt.enableflags = flags

    def max_penetration(self) -> np.ndarray:
        """Deepest penetration [N] (m, 0 without contact) of each arm's contacts found by the last mj_step1."""
        d, out = self.data, np.zeros(self.n)
        if d.ncon:
            arm = np.maximum(self._geom_arm[d.contact.geom1[:d.ncon]], self._geom_arm[d.contact.geom2[:d.ncon]])
            ok = arm >= 0
            np.maximum.at(out, arm[ok], -d.contact.dist[:d.ncon][ok])
        return out

    def site_pose(self, site: str = "tcp") -> tuple[np.ndarray, np.ndarray]:
        """World position [N, 3] (m) and rotation [N, 3, 3] of a site after the last step (kinematics of step1)."""
        sid = self._site_index(site)
        return self.data.site_xpos[sid] - self._origin, self.data.site_xmat[sid].reshape(-1, 3, 3)

    def contact_force(self, geom: str) -> np.ndarray:
        """World-frame force [N, 3] (N) that all contacts involving `geom` exert on `geom`, as the last `step`
        solved them: read it after `step()` (after `observe()`, mj_step1 has new contacts but their forces are not
        solved yet, and the numbers are meaningless)."""
        m, d = self.model, self.data
        arm_of = np.full(m.ngeom, -1)
        arm_of[[m.geom(p + geom).id for p in self._prefixes]] = np.arange(self.n)
        out = np.zeros((self.n, 3))
        if d.ncon == 0:
            return out
        geom1, geom2 = d.contact.geom1[:d.ncon], d.contact.geom2[:d.ncon]
        f6 = np.zeros(6)
        for c in np.flatnonzero((arm_of[geom1] >= 0) | (arm_of[geom2] >= 0)):
            mujoco.mj_contactForce(m, d, int(c), f6)
            f_world = d.contact.frame[c].reshape(3, 3).T @ f6[:3]  # force on geom2 from geom1, in world
            if arm_of[geom1[c]] >= 0:  # the frame's normal points from geom1 to geom2
                out[arm_of[geom1[c]]] -= f_world
            else:
                out[arm_of[geom2[c]]] += f_world
        return out


class ShardedPandaSim:
    """PandaSim's N arms split into `parts` MuJoCo models (contiguous ranges of arms) stepped in as many threads.

    The same interface as PandaSim (observe, push, step, reset, site_pose, contact_force, max_penetration, ncon);
    the tensors of `observe()` are [N, ...] as there. Why: MuJoCo is ~55 % of a peg-in-hole control period (mostly
    the peg's collision against the bore's boxes), and the Python bindings release the GIL in mj_step1 and
    mj_step2, so the parts' physics runs on separate cores. Each part places its arms where they sit in the grid of
    all N arms (PandaSim's `origins`), and the arms are independent in MuJoCo (no contacts between copies, one
    constraint island each), so every arm computes the same numbers as in one PandaSim(N), bit for bit
    (tests/test_sim_batched.py). The threads only change when the numbers are computed, never which.

    Args:
        n: number of arms (>= parts).
        parts: number of MuJoCo models and threads (1 works too: one part, no thread).
        origins: where the arms sit [n, 3] (m); default the grid of all n (PandaSim's `origins`).
        **kwargs: PandaSim's (tool, scene, q0, timestep, control_site, warmstart, contact_prefilter).
    """

    def __init__(self, n: int, parts: int = 2, origins: np.ndarray | None = None, **kwargs) -> None:
        if not 1 <= parts <= n:
            raise ValueError(f"ShardedPandaSim needs 1 <= parts <= n, got parts={parts}, n={n}")
        self.n = n
        if origins is None:
            origins = _grid(compose_mjcf(kwargs.get("tool", DEFAULT_TOOL), kwargs.get("scene", "")), n)
        origins = np.asarray(origins, dtype=np.float64).reshape(n, 3)
        bufs = _output_buffers(n)
        for name, buf in bufs.items():
            setattr(self, name, buf)
        self._ranges = [(int(r[0]), int(r[-1]) + 1) for r in np.array_split(np.arange(n), parts)]
        self.parts = [PandaSim(b - a, origins=origins[a:b], buffers={k: v[a:b] for k, v in bufs.items()}, **kwargs)
                      for a, b in self._ranges]
        self._origin = origins
        self.control_site = self.parts[0].control_site
        self._pool = ThreadPoolExecutor(max_workers=parts - 1, thread_name_prefix="PandaSim") if parts > 1 else None
        if self._pool is not None:
            weakref.finalize(self, self._pool.shutdown, wait=False)

    def _each(self, method: str, args: list[tuple] | None = None) -> list:
        """Call `method` of every part (part 0 in this thread, the others in the pool) and return the results."""
        args = args or [()] * len(self.parts)
        futures = [self._pool.submit(getattr(p, method), *a) for p, a in zip(self.parts[1:], args[1:])]
        first = getattr(self.parts[0], method)(*args[0])
        return [first] + [f.result() for f in futures]

    @property
    def models(self) -> list[mujoco.MjModel]:
        """The parts' MuJoCo models."""
        return [p.model for p in self.parts]

    @property
    def dt(self) -> float:
        """Simulation (= control) period [s]."""
        return self.parts[0].dt

    @property
    def time(self) -> float:
        """Simulated time of arm 0 [s] (since its last reset)."""
        return self.parts[0].time

    @property
    def ncon(self) -> int:
        """Number of MuJoCo contacts (all arms) found by the last mj_step1."""
        return sum(p.ncon for p in self.parts)

    def observe(self) -> SimState:
        """mj_step1 of every part (in parallel); PandaSim.observe's tensors [N, ...]."""
        self._each("_observe_arrays")
        return _sim_state(self, self.control_site is not None)

    def push(self, force_world: np.ndarray | torch.Tensor, site: str = "handle",
             torque_world: np.ndarray | torch.Tensor | None = None) -> None:
        """Apply a world-frame force [N, 3] (N) (and torque [N, 3], N m) at `site` during the next step()."""
        force = np.asarray(force_world, dtype=np.float64).reshape(self.n, 3)
        torque = None if torque_world is None else np.asarray(torque_world, np.float64).reshape(self.n, 3)
        for p, (a, b) in zip(self.parts, self._ranges):
            p.push(force[a:b], site=site, torque_world=None if torque is None else torque[a:b])

    def step(self, tau: torch.Tensor | np.ndarray) -> None:
        """Apply joint torques [N, 7] (N m) and run mj_step2 of every part (in parallel)."""
        tau = _arm_rows(tau, self.n, "tau", "N m")
        self._each("step", [(tau[a:b],) for a, b in self._ranges])

    def _by_part(self, arms: np.ndarray):  # noqa: ANN202
        """(part, mask over `arms` of its arms, their indices in the part) for each part holding some of `arms`."""
        for p, (a, b) in zip(self.parts, self._ranges):
            mine = (arms >= a) & (arms < b)
            if mine.any():
                yield p, mine, arms[mine] - a

    def reset(self, q: np.ndarray | torch.Tensor, qd: np.ndarray | torch.Tensor | None = None,
              idx: list[int] | None = None) -> None:
        """Set joint positions [N or len(idx), 7] (rad) and velocities (rad/s, default 0) and clear forces."""
        arms = np.arange(self.n) if idx is None else np.asarray(list(idx), dtype=np.intp).reshape(-1)
        q = _arm_rows(q, len(arms), "q", "rad")
        qd = np.zeros_like(q) if qd is None else _arm_rows(qd, len(arms), "qd", "rad/s")
        for p, mine, local in self._by_part(arms):
            p.reset(q[mine], qd[mine], idx=local.tolist())

    def contact_filter_counts(self) -> tuple[int, int]:
        """PandaSim.contact_filter_counts summed over the parts."""
        counts = [p.contact_filter_counts() for p in self.parts]
        return sum(c[0] for c in counts), sum(c[1] for c in counts)

    @property
    def contact_prefilter(self) -> bool:
        """Whether every part runs the exact contact pre-filter."""
        return all(p.contact_prefilter for p in self.parts)

    def park(self, idx: list[int] | np.ndarray) -> None:
        """PandaSim.park: set arms `idx` aside (collisions off, asleep once at rest) until their next reset."""
        arms = np.asarray(idx, dtype=np.intp).reshape(-1)
        for p, _, local in self._by_part(arms):
            p.park(local)

    def site_pose(self, site: str = "tcp") -> tuple[np.ndarray, np.ndarray]:
        """World position [N, 3] (m) and rotation [N, 3, 3] of a site after the last step (kinematics of step1)."""
        poses = [p.site_pose(site) for p in self.parts]
        return np.concatenate([x for x, _ in poses]), np.concatenate([r for _, r in poses])

    def contact_force(self, geom: str) -> np.ndarray:
        """World-frame force [N, 3] (N) that all contacts involving `geom` exert on `geom` (PandaSim.contact_force:
        read it after `step()`)."""
        return np.concatenate([p.contact_force(geom) for p in self.parts])

    def move_static_body(self, name: str, idx: list[int] | np.ndarray, offset: np.ndarray) -> None:
        """PandaSim.move_static_body of the arms `idx` on the parts that hold them."""
        arms = np.asarray(idx, dtype=np.intp).reshape(-1)
        offset = np.asarray(offset, dtype=np.float64).reshape(len(arms), 3)
        for p, mine, local in self._by_part(arms):
            p.move_static_body(name, local, offset[mine])

    def max_penetration(self) -> np.ndarray:
        """Deepest penetration [N] (m, 0 without contact) of each arm's contacts found by the last mj_step1."""
        return np.concatenate([p.max_penetration() for p in self.parts])
