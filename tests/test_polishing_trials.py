"""Polishing trials differ: each draws the plate's height (which the reference does not know), the first working zone
and the turn of the operator's moves; the plate is moved in MuJoCo, where the collision sees it."""

from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest

from a3cqp_rl.config import ExperimentConfig, config_from_dict, config_to_dict
from a3cqp_rl.robot import PandaSim
from a3cqp_rl.robot.scenes import plate_xml
from a3cqp_rl.robot.sim import ShardedPandaSim


def _polishing(**polishing) -> ExperimentConfig:
    d = config_to_dict(ExperimentConfig())
    d["panda"].update(scene="polishing", fd_axes=["z"])
    d["panda"]["polishing"].update(polishing)
    return config_from_dict(d)


def _plate_z(sim: PandaSim) -> np.ndarray:
    """World height of each arm's plate geom's centre [m], as MuJoCo's collision sees it."""
    return np.array([sim.data.geom_xpos[sim.model.geom(p + "plate").id, 2] for p in sim._prefixes])


def _disc_plate_distance(sim: PandaSim) -> np.ndarray:
    """MuJoCo's distance [m] between each arm's disc and its plate."""
    m, d = sim.model, sim.data
    return np.array([mujoco.mj_geomDistance(m, d, m.geom(p + "disc").id, m.geom(p + "plate").id, 1.0, None)
                     for p in sim._prefixes])


def test_each_trial_draws_its_plate_height_zone_and_turn_and_a_seed_repeats_them() -> None:
    from envs.panda import PandaEnv

    cfg = _polishing()
    c = cfg.panda.polishing
    env = PandaEnv(6, cfg, trial_seeds=[0, 1, 2, 3, 4, 5])
    env.reset()
    sc = env.scene
    dz = sc.plate_offset[:, 2]
    assert len(np.unique(dz)) == 6 and np.all(np.abs(dz) <= 2 * c.plate_top_spread + 1e-15)
    assert np.all(sc.plate_offset[:, :2] == 0.0)
    nominal = c.plate_top - 0.01  # the plate's centre: its top minus half its 20 mm
    np.testing.assert_allclose(_plate_z(env.sim), nominal + dz, rtol=0, atol=1e-12)
    start = np.array(c.plate_center) + np.array(c.start_offset)
    r = np.linalg.norm(sc.zone - start, axis=1)
    assert np.all(r <= c.zone_spread) and np.all(r > 0)
    assert np.all(np.abs(sc.turn) <= math.radians(c.relocation_turn_deg)) and len(np.unique(sc.turn)) == 6
    # the procedure's reference knows only the nominal plate: its polishing pose is preload below `plate_top`
    assert sc._polish_z() == c.plate_top - c.preload
    again = PandaEnv(2, cfg, trial_seeds=[3, 1])
    again.reset()
    np.testing.assert_array_equal(again.scene.plate_offset, sc.plate_offset[[3, 1]])
    np.testing.assert_array_equal(again.scene.zone, sc.zone[[3, 1]])
    np.testing.assert_array_equal(_plate_z(again.sim), _plate_z(env.sim)[[3, 1]])


def test_zero_spreads_give_the_fixed_procedure() -> None:
    from envs.panda import PandaEnv

    cfg = _polishing(plate_top_spread=0.0, zone_spread=0.0, relocation_turn_deg=0.0)
    c = cfg.panda.polishing
    env = PandaEnv(3, cfg, trial_seeds=[0, 1, 2])
    env.reset()
    assert np.all(env.scene.plate_offset == 0.0) and np.all(env.scene.turn == 0.0)
    np.testing.assert_array_equal(env.scene.zone, np.tile(np.array(c.plate_center) + np.array(c.start_offset), (3, 1)))
    np.testing.assert_allclose(_plate_z(env.sim), c.plate_top - 0.01, rtol=0, atol=1e-15)


@pytest.mark.parametrize("sharded", [False, True])
def test_a_moved_plate_is_where_the_collision_meets_it(sharded: bool) -> None:
    """Arm 1's plate 7 mm up, arm 2's 3 mm down: MuJoCo's disc-plate distance changes by exactly that, before and
    after steps, and with arms asleep (MuJoCo's sleeping computes static bodies once: the move must reach them)."""
    kw = dict(tool="disc_mesh", scene=plate_xml(tool_geom="disc"))
    sim = ShardedPandaSim(3, parts=2, **kw) if sharded else PandaSim(3, **kw)
    parts = sim.parts if sharded else [sim]
    sim.observe()
    before = np.concatenate([_disc_plate_distance(p) for p in parts])
    sim.move_static_body("plate", [1, 2], np.array([[0.0, 0.0, 0.007], [0.0, 0.0, -0.003]]))
    moved = np.concatenate([_disc_plate_distance(p) for p in parts])
    np.testing.assert_allclose(moved - before, [0.0, -0.007, 0.003], rtol=0, atol=1e-9)
    sim.park([0])  # arm 0 asleep from now on
    for _ in range(20):
        sim.observe()
        sim.step(np.zeros((3, 7)))
    sim.observe()
    z = np.concatenate([_plate_z(p) for p in parts])
    np.testing.assert_allclose(z - z[0], [0.0, 0.007, -0.003], rtol=0, atol=1e-12)
    sim.move_static_body("plate", [1, 2], np.zeros((2, 3)))  # back where the MJCF put them
    sim.observe()
    z = np.concatenate([_plate_z(p) for p in parts])
    np.testing.assert_allclose(z, z[0], rtol=0, atol=1e-15)


def test_only_static_scene_bodies_move() -> None:
    sim = PandaSim(2, tool="disc_mesh", scene=plate_xml(tool_geom="disc"))
    for name in ("link3", "no_such_body"):
        with pytest.raises(ValueError, match="no static body"):
            sim.move_static_body(name, [0], np.zeros((1, 3)))


@pytest.mark.parametrize("key,value", [("plate_top_spread", -0.001), ("zone_spread", float("nan")),
                                       ("relocation_turn_deg", -5.0)])
def test_the_spreads_are_validated(key: str, value: float) -> None:
    with pytest.raises(Exception, match=key):
        _polishing(**{key: value})
