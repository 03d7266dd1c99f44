"""Peg-in-hole scene: the bore holds the 0.25 mm clearance in MuJoCo, a centred peg drops in, one 2 mm off does not;
the collision mesh of the peg avoids a MuJoCo 4.0 EPA problem; scene MJCF composition."""

from __future__ import annotations

import math
from pathlib import Path

import mujoco
import numpy as np
import pytest

import a3cqp_rl.robot
from a3cqp_rl.config import load_config
from a3cqp_rl.exceptions import ConfigError
from a3cqp_rl.robot import PandaSim, compose_mjcf
from a3cqp_rl.robot.scenes import HoleGeometry, hole_block_xml, plate_xml

GEOM = HoleGeometry(center=(0.0, 0.0), top=0.1)


def _prism(n: int = 32, r: float = 0.01, half: float = 0.05) -> str:
    """The peg tool's collision mesh (tool_peg_mesh.xml): n-sided prism, corners on radius r."""
    v = [(r * math.cos(2 * math.pi * (k + 0.5) / n), r * math.sin(2 * math.pi * (k + 0.5) / n), z)
         for z in (-half, half) for k in range(n)]
    return " ".join(f"{x:.7f} {y:.7f} {z:g}" for x, y, z in v)


def _peg_model(x0: float, start: float, joints: str = "z", peg: str = "mesh") -> mujoco.MjModel:
    """A 1 kg peg on slide joints (the arm holds it: no free tilting) above or in the bore of GEOM."""
    slides = "".join(f'<joint name="{a}" type="slide" axis="{ax}"/>'
                     for a, ax in (("x", "1 0 0"), ("y", "0 1 0"), ("z", "0 0 1")) if a in joints)
    geom = 'type="mesh" mesh="p"' if peg == "mesh" else 'type="cylinder" size="0.01 0.05"'
    xml = f"""<mujoco><option timestep="0.001" integrator="implicitfast" impratio="10"/>
      <asset><mesh name="p" vertex="{_prism()}"/></asset>
      <worldbody>{hole_block_xml(GEOM)}
        <body name="peg" pos="{x0} 0 {GEOM.top + start + 0.05}">{slides}
          <geom name="peg" {geom} mass="1" contype="2" conaffinity="1"/>
        </body></worldbody></mujoco>"""
    return mujoco.MjModel.from_xml_string(xml)


def _push(m: mujoco.MjModel, force: tuple[float, float, float], seconds: float = 1.0) -> tuple[np.ndarray, float]:
    """Push the peg with a constant force; return (final peg tip position relative to the rim centre, the deepest
    contact penetration over the last 0.2 s [m])."""
    d = mujoco.MjData(m)
    body = m.body("peg").id
    worst = 0.0
    steps = int(seconds / m.opt.timestep)
    for k in range(steps):
        d.xfrc_applied[body, :3] = force
        mujoco.mj_step(m, d)
        if k > steps - 200 and d.ncon:
            worst = max(worst, -float(d.contact.dist[:d.ncon].min()))
    tip = d.xpos[body] - np.array([0.0, 0.0, 0.05])
    return tip - np.array([0.0, 0.0, GEOM.top]), worst


def test_centred_peg_drops_in_and_two_millimetres_off_rests_on_the_rim() -> None:
    tip, _ = _push(_peg_model(0.0, 0.002), (0.0, 0.0, -10.0))
    assert tip[2] == pytest.approx(-GEOM.depth, abs=0.5e-3)  # down to the floor of the 40 mm bore
    tip, pen = _push(_peg_model(0.0002, 0.002), (0.0, 0.0, -10.0))  # 0.2 mm off: inside the 0.25 mm clearance
    assert tip[2] == pytest.approx(-GEOM.depth, abs=0.5e-3)
    tip, pen = _push(_peg_model(0.002, 0.002), (0.0, 0.0, -10.0))
    assert abs(tip[2]) < 0.1e-3 and pen < 0.1e-3  # resting on the rim, not sinking into it


def test_bore_holds_the_radial_clearance_under_side_loads() -> None:
    for side in (5.0, 20.0, 100.0):
        tip, pen = _push(_peg_model(0.0, -0.01, joints="xyz"), (side, 0.0, 0.0), seconds=0.5)
        # radial clearance (20.5 - 20.0) / 2 = 0.25 mm at the faces, +0.05 mm at the 32-gons' corners
        assert 0.2e-3 < tip[0] < 0.31e-3, (side, tip)
        assert pen < 0.01e-3


def test_static_contact_starts_at_the_clearance() -> None:
    m = _peg_model(0.0, -0.01, joints="xyz")
    d = mujoco.MjData(m)
    for offset, touching in ((0.0, False), (0.2e-3, False), (0.35e-3, True)):
        d.qpos[:] = [offset, 0.0, 0.0]
        mujoco.mj_forward(m, d)
        assert (d.ncon > 0) == touching, offset


# Peg pose (world, hole of HoleGeometry() at (0.45, 0, 0.30)) recorded in a Panda run where MuJoCo 4.0's native
# GJK/EPA returned an 11 mm penetration with a sideways normal for the cylinder peg on the bore's edge.
_EPA_POS = np.array([0.4644125317, -0.0093606198, 0.3503738599])
_EPA_MAT = np.array([0.707606151, 0.7054470743, 0.0404717224, -0.7064146072, 0.7075888091, 0.0172185909,
                     -0.0164905333, -0.0407737968, 0.9990323117])


def _deepest_at_recorded_pose(peg: str) -> float:
    geom = 'type="mesh" mesh="p"' if peg == "mesh" else 'type="cylinder" size="0.01 0.05"'
    xml = f"""<mujoco><compiler angle="radian"/><option gravity="0 0 0"/>
      <asset><mesh name="p" vertex="{_prism()}"/></asset>
      <worldbody>{hole_block_xml(HoleGeometry())}
        <body name="peg" pos="0 0 0.5"><freejoint/><geom name="peg" {geom} contype="2" conaffinity="1"/></body>
      </worldbody></mujoco>"""
    m = mujoco.MjModel.from_xml_string(xml)
    d = mujoco.MjData(m)
    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, _EPA_MAT)
    d.qpos[:3], d.qpos[3:7] = _EPA_POS, q
    mujoco.mj_forward(m, d)
    return -float(d.contact.dist[:d.ncon].min()) if d.ncon else 0.0


def test_polytope_peg_avoids_the_cylinder_epa_problem() -> None:
    assert _deepest_at_recorded_pose("mesh") < 0.1e-3


def test_upstream_cylinder_epa_problem_still_present_or_fixed() -> None:
    """Documents why tool_peg_mesh.xml collides with a mesh: the cylinder gets a spurious ~11 mm penetration here."""
    if _deepest_at_recorded_pose("cylinder") < 1e-3:
        pytest.skip("MuJoCo's cylinder-box collision is exact here now; the peg could collide as a cylinder again")


def test_scene_composition_moves_tool_assets_and_replicates() -> None:
    text = compose_mjcf("peg_mesh", hole_block_xml(HoleGeometry()))
    assert text.count("<asset>") == 1 and text.index("<asset>") < text.index("<worldbody>")
    assert "<asset>" not in compose_mjcf("peg")
    sim = PandaSim(2, tool="peg_mesh", scene=hole_block_xml(HoleGeometry()) + plate_xml(center=(0.45, 0.4)))
    assert sim.model.nmesh == 2  # one collision mesh per copy
    m = sim.model
    assert m.geom_priority[m.geom("arm0/hole_block_seg0").id] > m.geom_priority[m.geom("arm0/peg").id]
    # the peg's mass comes from the drawn cylinder, the collision mesh has none
    assert m.geom_contype[m.geom("arm0/peg_visual").id] == 0


def test_hole_geometry_validation() -> None:
    with pytest.raises(ValueError, match="segments"):
        HoleGeometry(segments=4)
    with pytest.raises(ValueError, match="ring_radius"):
        HoleGeometry(bore_diameter=0.2)


def test_the_configs_hole_bounds_are_the_pegs_and_the_blocks() -> None:
    """PegInHoleConfig's check of hole_diameter reads the peg's diameter from its MJCF and the block's ring."""
    import xml.etree.ElementTree as ET

    from a3cqp_rl.config import HOLE_DIAMETER_MAX, PEG_DIAMETER

    assets = Path(a3cqp_rl.robot.__file__).parent / "assets"

    def xml(name: str) -> ET.Element:  # an MJCF fragment: several top-level elements
        return ET.fromstring(f"<fragment>{(assets / name).read_text()}</fragment>")

    (peg,) = [g for g in xml("tool_peg.xml").iter("geom") if g.get("name") == "peg"]
    assert 2 * float(peg.get("size")) == pytest.approx(PEG_DIAMETER, abs=1e-12)
    (hull,) = xml("tool_peg_mesh.xml").iter("mesh")  # the colliding prism of the Panda scenes
    xy = np.array(hull.get("vertex").split(), dtype=float).reshape(-1, 3)[:, :2]
    assert 2 * np.hypot(*xy.T).max() == pytest.approx(PEG_DIAMETER, abs=1e-6)
    assert HOLE_DIAMETER_MAX == pytest.approx(2 * HoleGeometry().ring_radius)


@pytest.mark.parametrize("needs_extraction", [True, False])
def test_next_cycle_starts_only_once_the_peg_left_the_bore(needs_extraction: bool) -> None:
    """At the end of the return home, arm 0's peg came out, arm 1's is still 10 mm deep in the bore: with
    `restart_needs_extraction` (the default) arm 1's episode ends there instead of its next approach dragging the peg."""
    from a3cqp_rl.config import OperatorConfig, PegInHoleConfig
    from envs.scenarios import Operator, PegInHole, SceneInput

    cfg = PegInHoleConfig(cycles=2, restart_needs_extraction=needs_extraction)
    scene = PegInHole(2, Operator(2, OperatorConfig(), 0.01), np.array([0.3, 0.0, 0.5]), np.eye(3), cfg)
    scene.reset(np.arange(2), [np.random.default_rng(k) for k in range(2)])
    scene.phase[:] = PegInHole.RETURN
    scene.extracted[:, 0] = [True, False]
    hole = np.array([*cfg.hole_center, cfg.hole_top])
    pos = np.stack([hole + [0.0, 0.0, 0.2], hole - [0.0, 0.0, 0.01]])
    z6 = np.zeros((2, 6))
    scene.update(SceneInput(t=np.full(2, cfg.return_time + 0.01), pos=pos, rot=np.tile(np.eye(3), (2, 1, 1)),
                            f_env=z6, f_ope=z6, f_d=z6, handle_pos=pos))
    assert scene.phase[0] == PegInHole.APPROACH and scene.cycle[0] == 1 and not scene.done[0]
    if needs_extraction:
        assert scene.phase[1] == PegInHole.DONE and scene.done[1] and scene.cycle[1] == 0
    else:
        assert scene.phase[1] == PegInHole.APPROACH and scene.cycle[1] == 1


def test_insertion_time_splits_at_the_tip_one_millimetre_inside_the_bore() -> None:
    """Arm 0 touches the rim at 1.0 s, its tip is 1 mm inside the bore at 3.0 s and at the success depth at 3.5 s;
    arm 1 dips 1 mm below the rim beside the bore (outside its radius), which is not in the bore."""
    from a3cqp_rl.config import OperatorConfig, PegInHoleConfig
    from envs.scenarios import Operator, PegInHole, SceneInput

    cfg = PegInHoleConfig(operator_disengage=False)
    scene = PegInHole(2, Operator(2, OperatorConfig(), 0.01), np.array([0.3, 0.0, 0.5]), np.eye(3), cfg)
    scene.reset(np.arange(2), [np.random.default_rng(k) for k in range(2)])
    scene.phase[:] = PegInHole.INSERT
    hole = np.array([*cfg.hole_center, cfg.hole_top])
    off = np.array([0.5 * cfg.hole_diameter + 1e-3, 0.0, 0.0])
    z6, press = np.zeros((2, 6)), np.zeros((2, 6))
    press[:, 2] = 5.0  # above the contact threshold
    for t, depth in ((1.0, 0.0), (2.0, 0.0005), (3.0, 0.001), (3.2, 0.01), (3.5, cfg.success_depth)):
        pos = np.stack([hole - [0.0, 0.0, depth], hole + off - [0.0, 0.0, min(depth, 0.001)]])
        scene.update(SceneInput(t=np.full(2, t), pos=pos, rot=np.tile(np.eye(3), (2, 1, 1)), f_env=press,
                                f_ope=z6, f_d=z6, handle_pos=pos))
    m = scene.metrics()
    assert m["to_bore_time"][0, 0] == pytest.approx(2.0) and m["bore_descent_time"][0, 0] == pytest.approx(0.5)
    assert m["to_bore_time"][0, 0] + m["bore_descent_time"][0, 0] == pytest.approx(m["insertion_time"][0, 0])
    assert np.isnan(m["to_bore_time"][1, 0]) and not m["success"][1, 0]


def test_a_disengagement_counts_as_one_that_can_pull_the_peg_out_only_with_the_peg_in_the_bore() -> None:
    """Both arms reach the time limit: arm 0 with its tip 5 mm inside the bore, arm 1 resting 1 mm above the rim."""
    from a3cqp_rl.config import OperatorConfig, PegInHoleConfig
    from envs.scenarios import Operator, PegInHole, SceneInput

    cfg = PegInHoleConfig(time_limit=1.0, disengage_failed=True)
    scene = PegInHole(2, Operator(2, OperatorConfig(), 0.01), np.array([0.3, 0.0, 0.5]), np.eye(3), cfg)
    scene.reset(np.arange(2), [np.random.default_rng(k) for k in range(2)])
    scene.phase[:] = PegInHole.INSERT
    hole = np.array([*cfg.hole_center, cfg.hole_top])
    pos = np.stack([hole - [0.0, 0.0, 0.005], hole + [0.0, 0.0, 0.001]])
    z6, press = np.zeros((2, 6)), np.zeros((2, 6))
    press[:, 2] = 5.0
    for t in (1.0, 2.5):  # first contact, then past the time limit
        scene.update(SceneInput(t=np.full(2, t), pos=pos, rot=np.tile(np.eye(3), (2, 1, 1)), f_env=press, f_ope=z6,
                                f_d=z6, handle_pos=pos))
    assert (scene.phase == PegInHole.DISENGAGE).all()
    assert scene.metrics()["in_bore_at_grasp"][:, 0].tolist() == [True, False]
    assert scene.extracted[1, 0]  # the tip above the rim reads as 'out' from the start: hence the flag


@pytest.mark.parametrize("cycles, disengage_failed", [(1, False), (1, True), (2, False)])
def test_a_single_trial_not_inserted_by_the_time_limit_ends_there(cycles: int, disengage_failed: bool) -> None:
    """Arm 0 is inserted, arm 1 sits on the rim past the time limit. The operator grasps arm 0's handle either way;
    arm 1's only with `disengage_failed` or a next cycle to clear the block for, else its episode ends."""
    from a3cqp_rl.config import OperatorConfig, PegInHoleConfig
    from envs.scenarios import Operator, PegInHole, SceneInput

    cfg = PegInHoleConfig(time_limit=1.0, cycles=cycles, disengage_failed=disengage_failed)
    op = Operator(2, OperatorConfig(), 0.01)
    scene = PegInHole(2, op, np.array([0.3, 0.0, 0.5]), np.eye(3), cfg)
    scene.reset(np.arange(2), [np.random.default_rng(k) for k in range(2)])
    scene.phase[:] = PegInHole.INSERT
    hole = np.array([*cfg.hole_center, cfg.hole_top])
    z6, press = np.zeros((2, 6)), np.zeros((2, 6))
    press[:, 2] = 5.0
    for t, depth in ((1.0, 0.0), (1.5, cfg.success_depth), (2.5, cfg.success_depth)):
        pos = np.stack([hole - [0.0, 0.0, depth], hole + [0.0, 0.0, 0.0001]])
        scene.update(SceneInput(t=np.full(2, t), pos=pos, rot=np.tile(np.eye(3), (2, 1, 1)), f_env=press, f_ope=z6,
                                f_d=z6, handle_pos=pos))
    m = scene.metrics()
    assert m["success"][:, 0].tolist() == [True, False]
    assert scene.phase[0] == PegInHole.DISENGAGE and op.active[0] and not scene.done[0]
    pulled = disengage_failed or cycles > 1
    assert scene.phase[1] == (PegInHole.DISENGAGE if pulled else PegInHole.DONE)
    assert bool(op.active[1]) == pulled and bool(scene.done[1]) != pulled


def test_the_time_cost_is_paid_from_the_first_contact_until_the_insertion_ends() -> None:
    """Arm 0 touches the rim at 1.0 s and is inserted at 2.0 s; arm 1 never touches; without time_cost no term."""
    from a3cqp_rl.config import OperatorConfig, PegInHoleConfig
    from envs.scenarios import Operator, PegInHole, SceneInput

    def scene_with(cost: float) -> PegInHole:
        cfg = PegInHoleConfig(operator_disengage=False, time_cost=cost)
        s = PegInHole(2, Operator(2, OperatorConfig(), 0.01), np.array([0.3, 0.0, 0.5]), np.eye(3), cfg)
        s.reset(np.arange(2), [np.random.default_rng(k) for k in range(2)])
        s.phase[:] = PegInHole.INSERT
        return s

    scene = scene_with(1.5)
    cfg = scene.cfg
    hole = np.array([*cfg.hole_center, cfg.hole_top])
    z6 = np.zeros((2, 6))
    press = z6.copy()
    press[0, 2] = 5.0
    costs = []
    for t, depth in ((0.5, -0.01), (1.0, 0.0), (1.5, 0.01), (2.0, cfg.success_depth), (2.5, cfg.success_depth)):
        pos = np.stack([hole - [0.0, 0.0, depth], hole + [0.0, 0.0, 0.02]])
        scene.update(SceneInput(t=np.full(2, t), pos=pos, rot=np.tile(np.eye(3), (2, 1, 1)),
                                f_env=press if t >= 1.0 else z6, f_ope=z6, f_d=z6, handle_pos=pos))
        costs.append(scene.reward_term().copy())
    assert [c[0] for c in costs] == [0.0, -1.5, -1.5, 0.0, 0.0]  # from the contact; the success ends it
    assert all(c[1] == 0.0 for c in costs)
    assert scene_with(0.0).reward_term() is None
    with pytest.raises(ConfigError, match="time_cost"):
        load_config(None, {"panda": {"peg_in_hole": {"time_cost": -1.0}}})


def test_the_hands_intrinsic_damping_acts_on_the_present_velocity_the_rest_on_the_delayed_state() -> None:
    """A hand holding still at its attractor: the handle starts moving at 0.1 m/s along x. The delayed spring-damper
    still sees the handle at rest (0.1 s ago); only `intrinsic_damping` answers at once, with −D_i v."""
    from a3cqp_rl.config import OperatorConfig
    from envs.scenarios import Operator

    dt = 0.001
    forces = {}
    for d_i in (0.0, 30.0):
        op = Operator(1, OperatorConfig(intrinsic_damping=d_i, noise=0.0, speed=1e-9, grip_time=1e-6), dt)
        rest, rot, zero = np.zeros((1, 3)), np.eye(3)[None], np.zeros((1, 3))
        op.update(np.zeros(1), rest, rot)
        op.grasp(np.array([0]), rest.copy(), np.zeros(1))  # hold the handle where it is
        t = np.zeros(1)
        for _ in range(50):  # at rest: the delayed history fills with the resting state
            t += dt
            op.wrench(t, rest, zero, rot, zero)
        t += dt
        forces[d_i], _ = op.wrench(t, rest, np.array([[0.1, 0.0, 0.0]]), rot, zero)
    np.testing.assert_allclose(forces[0.0], 0.0, atol=1e-12)
    np.testing.assert_allclose(forces[30.0], [[-3.0, 0.0, 0.0]], atol=1e-9)
    from a3cqp_rl.config import config_from_dict
    from a3cqp_rl.exceptions import ConfigError

    with pytest.raises(ConfigError, match="intrinsic_damping"):
        config_from_dict({"panda": {"operator": {"intrinsic_damping": -1.0}}})
