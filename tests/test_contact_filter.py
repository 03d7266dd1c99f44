"""The C contact filter (a3cqp_rl.robot.contact_filter): it drops mesh-box pairs in the peg's bore and leaves every
contact, hence the simulation, as MuJoCo's own filter has it, bit for bit."""

from __future__ import annotations

import ctypes

import mujoco
import numpy as np
import pytest

from a3cqp_rl.robot import contact_filter
from a3cqp_rl.robot.scenes import HoleGeometry, hole_block_xml

pytestmark = pytest.mark.skipif(contact_filter._LIB.get() is None, reason="the C contact filter is not built")


def _peg_in_block(x: float, z: float, tilt_deg: float) -> tuple[mujoco.MjModel, mujoco.MjData]:
    """A free peg (the peg tool's 32-sided prism) above or in the bore of the peg-in-hole block."""
    peg = open(contact_filter.Path(contact_filter.__file__).parent / "assets" / "tool_peg_mesh.xml").read()
    asset = peg[peg.index("<asset>"):peg.index("</asset>") + len("</asset>")]
    xml = (f'<mujoco><option timestep="0.001"/>{asset}<worldbody>{hole_block_xml(HoleGeometry())}'
           f'<body pos="{x} 0 {z}" euler="{tilt_deg} 0 0"><freejoint/>'
           f'<geom type="mesh" mesh="peg_hull" contype="2" conaffinity="1" mass="0.1"/></body></worldbody></mujoco>')
    m = mujoco.MjModel.from_xml_string(xml)
    return m, mujoco.MjData(m)


@pytest.fixture
def own_filter():
    """MuJoCo's own filter during the test body, whatever the process had installed; restored afterwards."""
    before = contact_filter.installed()
    contact_filter.uninstall()
    yield
    if before:
        contact_filter.install()


def _contacts(m: mujoco.MjModel, d: mujoco.MjData) -> dict[str, np.ndarray]:
    mujoco.mj_forward(m, d)
    c = d.contact
    return {k: getattr(c, k)[:d.ncon].copy() for k in ("geom1", "geom2", "dist", "pos", "frame")}


# centred without contact, on the floor, tilted against the wall, resting on the rim 2 mm off
POSES = [(0.45, 0.33, 0.0), (0.45, 0.27, 0.0), (0.4502, 0.27, 0.5), (0.452, 0.349, 0.0), (0.4525, 0.30, 1.0)]


@pytest.mark.parametrize("pose", POSES)
def test_the_filter_finds_the_same_contacts_and_drops_pairs(pose, own_filter) -> None:
    m, d = _peg_in_block(*pose)
    ref = _contacts(m, d)
    lib = contact_filter._LIB.get()
    raw = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int, ctypes.c_int)(
        ctypes.cast(lib, ctypes.c_void_p).value)  # the bound CFUNCTYPE
    calls, drops = [0], [0]

    def counting(m_, d_, g1, g2):  # the C filter, counted (a Python callback, for the count only)
        calls[0] += 1
        r = raw(m._address, d._address, g1, g2)
        drops[0] += r
        return r

    mujoco.set_mjcb_contactfilter(counting)
    try:
        got = _contacts(m, d)
    finally:
        mujoco.set_mjcb_contactfilter(None)
    assert contact_filter.install()
    fast = _contacts(m, d)
    for k in ref:
        np.testing.assert_array_equal(got[k], ref[k])
        np.testing.assert_array_equal(fast[k], ref[k])
    assert drops[0] >= 8  # of the ~28 boxes that pass MuJoCo's own filters (all of them when nothing touches)
    assert drops[0] < calls[0] or len(ref["dist"]) == 0


def test_a_peg_dropped_into_the_bore_moves_the_same_with_the_filter(own_filter) -> None:
    runs = []
    for use in (False, True):
        if use:
            assert contact_filter.install()
        m, d = _peg_in_block(0.4504, 0.34, 0.8)
        for _ in range(400):
            mujoco.mj_step(m, d)
        runs.append((d.qpos.copy(), d.qvel.copy(), d.ncon))
    assert runs[0][2] > 0  # it has landed
    np.testing.assert_array_equal(runs[1][0], runs[0][0])
    np.testing.assert_array_equal(runs[1][1], runs[0][1])
