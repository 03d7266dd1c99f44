"""The exact tool-box contact pre-filter (a3cqp_rl.robot.contact_filter): it drops pairs, yet every contact and
every state stay bit for bit; MuJoCo's contype/conaffinity test still holds for every model; another contact filter
is left alone."""

from __future__ import annotations

import logging

import mujoco
import numpy as np
import pytest
import torch

from a3cqp_rl.robot import PandaSim, contact_filter
from a3cqp_rl.robot.scenes import HoleGeometry, hole_block_xml
from tests.test_panda_scene import _prism
from tests.test_sim_batched import table_scene

GEOM = HoleGeometry(center=(0.0, 0.0), top=0.1)

pytestmark = pytest.mark.skipif(contact_filter._library.get() is None, reason="contact_filter.c not built")


def _peg_in_bore(x0: float) -> mujoco.MjModel:
    """A peg on x, y, z slides above the bore of GEOM, `x0` off its axis, tilted 2 degrees about y."""
    slides = "".join(f'<joint name="{a}" type="slide" axis="{ax}"/>'
                     for a, ax in (("x", "1 0 0"), ("y", "0 1 0"), ("z", "0 0 1")))
    xml = f"""<mujoco><option timestep="0.001" integrator="implicitfast" impratio="10"/>
      <asset><mesh name="p" vertex="{_prism()}"/></asset>
      <worldbody>{hole_block_xml(GEOM)}
        <body name="peg" pos="{x0} 0 {GEOM.top + 0.052}" euler="0 2 0">{slides}
          <geom name="peg" type="mesh" mesh="p" mass="1" contype="2" conaffinity="1"/>
        </body></worldbody></mujoco>"""
    return mujoco.MjModel.from_xml_string(xml)


def _run(m: mujoco.MjModel, filtered: bool, steps: int = 1500) -> tuple[np.ndarray, list, tuple[int, int]]:
    """Push the peg down and toward the axis; (qpos per step, every step's contacts, the filter's counts)."""
    d = mujoco.MjData(m)
    reg = None
    if filtered:
        boxes = np.flatnonzero(m.geom_type == int(mujoco.mjtGeom.mjGEOM_BOX))
        reg = contact_filter.attach(m, d, [m.geom("peg").id], boxes)
        assert reg is not None
    qpos, contacts = [], []
    try:
        for _ in range(steps):
            d.xfrc_applied[m.body("peg").id, :3] = (-3.0, 0.0, -10.0)
            mujoco.mj_step(m, d)
            qpos.append(d.qpos.copy())
            contacts.append([(c.geom[0], c.geom[1], c.dist, *c.pos, *c.frame) for c in d.contact])
        return np.array(qpos), contacts, (reg.counts() if reg else (0, 0))
    finally:
        if reg:
            reg.detach()


@pytest.mark.parametrize("margin", [0.0, 0.001])
def test_the_prefilter_drops_pairs_yet_every_contact_and_state_stay_bit_for_bit(margin: float) -> None:
    """`margin` on every geom: MuJoCo adds the pair's two (contacts up to 2 mm apart), and so must the filter."""
    m = _peg_in_bore(0.002)  # on the rim, pushed over it and down the bore
    m.geom_margin[:] = margin
    q0, c0, _ = _run(m, filtered=False)
    q1, c1, (seen, dropped) = _run(m, filtered=True)
    assert q0[-1, 2] < -0.02  # the peg went down the bore: contacts on the rim, then on the bore's walls
    assert sum(map(len, c0)) > 500
    assert np.array_equal(q0, q1) and c0 == c1
    assert seen > 0 and dropped > (0.3 if margin == 0 else 0.1) * seen


def test_callback_keeps_mujocos_contype_conaffinity_test_for_any_model() -> None:
    m = _peg_in_bore(0.002)
    contact_filter.attach(m, mujoco.MjData(m), [m.geom("peg").id], [m.geom("hole_block_seg0").id])  # installs
    assert mujoco.get_mjcb_contactfilter() is not None
    xml = """<mujoco><worldbody>
      <geom name="a" type="box" size="0.1 0.1 0.1" contype="1" conaffinity="1"/>
      <body pos="-0.12 0 0.15"><freejoint/><geom name="b" type="sphere" size="0.1" contype="2" conaffinity="2"/></body>
      <body pos="0.12 0 0.15"><freejoint/><geom name="c" type="sphere" size="0.1" contype="2" conaffinity="1"/></body>
    </worldbody></mujoco>"""
    other = mujoco.MjModel.from_xml_string(xml)  # never registered

    def pairs() -> set:
        d = mujoco.MjData(other)
        mujoco.mj_forward(other, d)
        return {tuple(sorted((other.geom(c.geom[0]).name, other.geom(c.geom[1]).name))) for c in d.contact}

    ours = mujoco.get_mjcb_contactfilter()
    with_ours = pairs()
    mujoco.set_mjcb_contactfilter(None)
    try:
        without = pairs()
    finally:
        mujoco.set_mjcb_contactfilter(ours)
    assert with_ours == without == {("a", "c")}  # b overlaps a, but 2 & 1 = 0 both ways


def test_a_registration_dropped_without_detach_frees_its_slot_and_holds_its_model_until_then() -> None:
    """The filter finds a registration by its model's and data's addresses: one left registered after they were
    freed would be matched by a model and data allocated there later. Registrations hold both, and free their slot
    when collected: 300 attach-and-drop rounds (the registry has 256 slots) all register."""
    m = _peg_in_bore(0.0)
    peg, box = [m.geom("peg").id], [m.geom("hole_block_seg0").id]
    for _ in range(300):
        assert contact_filter.attach(m, mujoco.MjData(m), peg, box) is not None  # dropped at once
    other = _peg_in_bore(0.0)
    reg = contact_filter.attach(other, mujoco.MjData(other), peg, box)  # the data: held by the registration only
    held_m, held_d = reg._held[:2]
    assert held_m is other and isinstance(held_d, mujoco.MjData) and held_d.model is other
    reg.detach()
    reg.detach()  # once
    assert reg._held is None


def test_another_contact_filter_is_left_alone(monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
                                              ) -> None:
    before = mujoco.get_mjcb_contactfilter()
    monkeypatch.setattr(contact_filter, "_state", {})  # as in a process where ours was never installed

    def theirs(m, d, g1, g2):  # noqa: ANN001, ANN202
        return 0

    mujoco.set_mjcb_contactfilter(theirs)
    try:
        m = _peg_in_bore(0.0)
        peg, box = [m.geom("peg").id], [m.geom("hole_block_seg0").id]
        with caplog.at_level(logging.WARNING, logger="a3cqp_rl.robot.contact_filter"):
            assert contact_filter.attach(m, mujoco.MjData(m), peg, box) is None
        assert mujoco.get_mjcb_contactfilter() is theirs
        assert "already set" in caplog.text
    finally:
        mujoco.set_mjcb_contactfilter(before)


def test_the_bounding_cylinder_holds_every_vertex_of_the_peg_and_the_disc() -> None:
    sim = PandaSim(1, tool="peg_mesh")
    m = sim.model
    g = m.geom("peg").id
    axis, h, rho = contact_filter.bounding_cylinder(m, g)
    assert axis == 2 and h == pytest.approx(0.05, rel=1e-6) and rho == pytest.approx(0.01, rel=1e-6)
    disc = PandaSim(1, tool="disc_mesh").model
    mesh_geoms = np.flatnonzero(disc.geom_type == int(mujoco.mjtGeom.mjGEOM_MESH))
    assert len(mesh_geoms)
    for g in mesh_geoms:
        axis, h, rho = contact_filter.bounding_cylinder(disc, g)
        mesh = disc.geom_dataid[g]
        v = disc.mesh_vert[disc.mesh_vertadr[mesh]:disc.mesh_vertadr[mesh] + disc.mesh_vertnum[mesh]]
        assert h < rho  # a disc: the short axis
        assert (np.abs(v[:, axis]) <= h).all() and (np.linalg.norm(np.delete(v, axis, 1), axis=1) <= rho).all()


def test_panda_sim_registers_its_tool_mesh_and_computes_the_same_numbers() -> None:
    """Two arms with the peg's collision mesh pressed on a table: with the pre-filter or without, every output
    of 300 steps bit for bit; the filter saw the tool-table pairs."""
    out, press = {}, torch.tensor([0.0, 0.0, -25.0, 0.0, 0.0, 0.0], dtype=torch.float64)[:, None]
    for on in (True, False):
        sim = PandaSim(2, tool="peg_mesh", scene=table_scene(), contact_prefilter=on)
        rows = []
        for _ in range(300):
            s = sim.observe()
            sim.step(s.bias + (s.kin.jac.transpose(1, 2) @ press)[..., 0])
            rows.append(np.concatenate([s.q.numpy().ravel(), s.f_env.numpy().ravel()]))
        out[on] = (np.array(rows), sim.contact_filter_counts(), sim.ncon)
    assert np.array_equal(out[True][0], out[False][0])
    assert out[True][2] > 0  # in contact at the end
    assert out[True][1][0] > 0 and out[False][1] == (0, 0)



def test_two_models_stepped_in_two_threads_each_filtered_compute_what_one_unfiltered_model_computes() -> None:
    """ShardedPandaSim's parts run mj_step1 at the same time, each registered with the filter: the same numbers as
    one PandaSim without it, bit for bit, and both parts' pairs went through the filter."""
    from a3cqp_rl.robot.sim import ShardedPandaSim

    n, press = 4, torch.tensor([0.0, 0.0, -25.0, 0.0, 0.0, 0.0], dtype=torch.float64)[:, None]
    one = PandaSim(n, tool="peg_mesh", scene=table_scene(), contact_prefilter=False)
    two = ShardedPandaSim(n, parts=2, tool="peg_mesh", scene=table_scene())
    assert two.contact_prefilter and not one.contact_prefilter
    for _ in range(300):
        a, b = one.observe(), two.observe()
        assert torch.equal(a.q, b.q) and torch.equal(a.f_env, b.f_env)
        tau = a.bias + (a.kin.jac.transpose(1, 2) @ press)[..., 0]
        one.step(tau)
        two.step(tau)
    assert one.ncon > 0
    assert all(p.contact_filter_counts()[0] > 0 for p in two.parts)


def test_every_pair_the_filter_drops_is_farther_apart_than_its_slack_and_the_slab_bound_drops_more() -> None:
    """Random poses of the peg's prism about the bore's rim (its tip up to 12 mm off the axis and within 2 mm of the
    rim's height, tilted up to 5 degrees; overlapping poses too): for every peg-box pair the filter drops, MuJoCo's
    own distance (mj_geomDistance, GJK on the same meshes) is above the slack. The bound through a box's slab drops
    more than a tenth of the pairs that the planes normal to the box's axes keep (a tilted peg's end reaching a
    box's slab with a part above the box's top)."""
    import ctypes

    xml = f"""<mujoco><asset><mesh name="p" vertex="{_prism()}"/></asset>
      <worldbody>{hole_block_xml(GEOM)}
        <body name="peg"><freejoint/><geom name="peg" type="mesh" mesh="p" mass="1" contype="2" conaffinity="1"/>
        </body></worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    boxes = np.flatnonzero((m.geom_type == int(mujoco.mjtGeom.mjGEOM_BOX)) & (m.geom_contype > 0))  # not the stand
    peg = m.geom("peg").id
    reg = contact_filter.attach(m, d, [peg], boxes)
    assert reg is not None
    lib = contact_filter._library.get()
    drop = lib.cf_filter
    drop.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int]
    drop.restype = ctypes.c_int
    rng = np.random.default_rng(0)
    fromto = np.zeros(6)
    dropped = kept = 0
    try:
        for _ in range(300):
            tilt, heading = np.deg2rad(rng.uniform(0.0, 5.0)), rng.uniform(0.0, 2 * np.pi)
            off, towards = rng.uniform(0.0, 0.012), rng.uniform(0.0, 2 * np.pi)
            axis = np.array([np.cos(heading), np.sin(heading), 0.0])
            quat = np.zeros(4)
            mujoco.mju_axisAngle2Quat(quat, axis, tilt)
            tip = np.array([off * np.cos(towards), off * np.sin(towards), GEOM.top + rng.uniform(-0.002, 0.002)])
            up = np.zeros(3)
            mujoco.mju_rotVecQuat(up, np.array([0.0, 0.0, 1.0]), quat)
            d.qpos[:3], d.qpos[3:] = tip + 0.05 * up, quat  # the prism's centre 50 mm up its axis
            mujoco.mj_kinematics(m, d)
            for b in boxes:
                if drop(m._address, d._address, peg, int(b)):
                    dropped += 1
                    assert mujoco.mj_geomDistance(m, d, peg, int(b), 0.01, fromto) > contact_filter.SLACK - 1e-6
                else:
                    kept += 1
        seen, out, by_slab = reg.counts_by_test()
    finally:
        reg.detach()
    assert dropped > 0.3 * (dropped + kept) and kept > 0
    assert (seen, out) == (dropped + kept, dropped) and by_slab > 0.1 * (kept + by_slab)


def test_roles_zeroed_in_place_drop_nothing_and_restored_drop_again() -> None:
    """`Registration.role` is the array the C filter reads (docs/experiments/collision_floor.py zeroes it to time
    MuJoCo's collision without the filter): zeroed, no pair is dropped; restored, the same pairs are."""
    m = _peg_in_bore(0.0006)
    d = mujoco.MjData(m)
    boxes = np.flatnonzero(m.geom_type == int(mujoco.mjtGeom.mjGEOM_BOX))
    reg = contact_filter.attach(m, d, [m.geom("peg").id], boxes)
    d.qpos[2] = -0.03  # the peg lowered 30 mm toward the bore: some of its boxes near, most far
    mujoco.mj_forward(m, d)
    role = reg.role
    assert role is not None and set(np.flatnonzero(role == 2)) == set(boxes) and role[m.geom("peg").id] == 1

    def dropped() -> int:
        before = reg.counts()[1]
        mujoco.mj_collision(m, d)
        return reg.counts()[1] - before

    first = dropped()
    assert first > 0
    saved = role.copy()
    role[:] = 0
    assert dropped() == 0
    role[:] = saved
    assert dropped() == first
    reg.detach()
    assert reg.role is None

