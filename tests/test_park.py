"""Parking finished arms (PandaSim.park, PandaEnv.park, `evaluate(park=True)`): their contacts stop, the arms still
running move bit for bit as before, and an evaluation's results do not change (in worker processes: up to
round-off)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from a3cqp_rl.robot.sim import PandaSim

# a box whose top face sits 0.5 mm above the peg's tip at the home pose: every arm starts in contact
_TIP = (0.306890567, 0.0, 0.464582052)
_BOX = (f'<body name="stop" pos="{_TIP[0]} {_TIP[1]} {_TIP[2] - 0.0095}"><geom name="stop" type="box" '
        'size="0.03 0.03 0.01" contype="1" conaffinity="2" priority="1"/></body>')


def _run(park: list[int], steps: int = 150) -> tuple[np.ndarray, np.ndarray, PandaSim]:
    sim = PandaSim(3, tool="peg_mesh", scene=_BOX)
    sim.park(park)
    qs, pens = [], []
    for _ in range(steps):
        s = sim.observe()
        pens.append(sim.max_penetration())
        sim.step(0.97 * s.bias)  # 97 % of gravity compensation: the arm sags onto the box
        qs.append(s.q.numpy().copy())
    return np.array(qs), np.array(pens), sim


def test_a_parked_arm_stops_colliding_and_the_others_run_on_bit_for_bit() -> None:
    q_ref, pen_ref, _ = _run([])
    q, pen, sim = _run([1])
    assert (pen_ref[:, 1] > 0).all() and (pen_ref[:, 0] > 0).all()  # all touch the box without parking
    assert (pen[:, 1] == 0).all() and (pen[:, [0, 2]] > 0).all()  # the parked one no longer does, the others do
    assert np.abs(q_ref[:, 1] - q[:, 1]).max() > 1e-6  # ... and it moves otherwise (it sinks into the box)
    np.testing.assert_array_equal(q[:, [0, 2]], q_ref[:, [0, 2]])  # their contact solves are their own
    sim.reset(np.tile(sim._q[1], (1, 1)), idx=[1])  # a reset arm collides again
    sim.observe()
    assert sim.max_penetration()[1] > 0


def test_a_parked_arm_held_by_h_plus_g_sleeps_until_its_reset() -> None:
    """At rest under h + g a parked arm sleeps from the step it was parked on: MuJoCo leaves it where it is (pushes
    and torques do not move it) and its read-out keeps its values; a reset wakes it at its new pose; the others run
    on bit for bit."""
    from a3cqp_rl.robot import sense

    q_ref, _, _ = _run([])
    sim = PandaSim(3, tool="peg_mesh", scene=_BOX)
    for k in range(150):
        if k == 20:
            sim.park([1])
        s = sim.observe()
        if k < 20:
            tau = 0.97 * s.bias.numpy()
        else:  # the parked arm held by h + g, as the controller's inactive robots are
            tau = s.bias.numpy() * np.array([[0.97], [1.0], [0.97]])
        sim.step(tau)
        np.testing.assert_array_equal(s.q.numpy()[[0, 2]], q_ref[k, [0, 2]])
        if k == 21:
            q_asleep, read = s.q.numpy()[1].copy(), {k: v.numpy()[1].copy() for k, v in (("q", s.q), ("bias", s.bias))}
    assert sim.data.ntree_awake == 2 and sim.data.tree_awake[sim._arm_tree[1]] == 0
    s = sim.observe()
    np.testing.assert_array_equal(s.q.numpy()[1], q_asleep)  # not moved for 128 steps
    if sense.observer(sim) is not None:  # the C read-out skipped it: its values are those of its last read-out
        np.testing.assert_array_equal(s.bias.numpy()[1], read["bias"])
    sim.push(np.array([[0.0, 0.0, 0.0], [5.0, 0.0, 0.0], [0.0, 0.0, 0.0]]), site="handle")
    sim.step(s.bias.numpy() + 3.0)
    np.testing.assert_array_equal(sim.observe().q.numpy()[1], q_asleep)  # frozen: pushes and torques do not move it
    assert sim.data.ntree_awake == 2
    q_new = q_asleep + 0.2
    sim.reset(q_new[None], idx=[1])  # a reset wakes it where it is put, its kinematics with it
    assert sim.data.ntree_awake == 3
    s = sim.observe()
    np.testing.assert_array_equal(s.q.numpy()[1], q_new)
    pos, _ = sim.site_pose()
    sim2 = PandaSim(1, tool="peg_mesh", scene=_BOX, q0=tuple(q_new))
    np.testing.assert_allclose(pos[1], sim2.site_pose()[0][0], atol=1e-12)


@pytest.mark.slow
def test_an_evaluation_gives_the_same_results_parked_or_not_and_in_two_worker_processes() -> None:
    from a3cqp_rl.config import config_from_dict
    from envs.panda_eval import evaluate

    torch.set_num_threads(1)
    cfg = config_from_dict({"panda": {"peg_in_hole": {"settle_time": 0.1, "approach_time": 1.0, "align_time": 2.0,
                                                      "time_limit": 2.0, "return_time": 0.5}}})
    kw = dict(trials=2, seed=0, config=cfg, controllers=("ik_fc", "ik"), progress=False)
    base = evaluate("peg_in_hole", None, park=False, **kw)
    parked, split = evaluate("peg_in_hole", None, park=True, **kw), evaluate("peg_in_hole", None, workers=2, **kw)
    for c in ("ik_fc", "ik"):
        a, b = base.per_trial[c], parked.per_trial[c]
        assert a.keys() == b.keys()
        assert a["success"] == b["success"] and a["extracted"] == b["extracted"]
        for key in a:  # parking changes no arm's motion: every per-trial value to float round-off (the metrics'
            # running sums over arm subsets may add in another order, and the controller's subset of live arms is a
            # batch of another size: 3e-12 of the operator's mean force here), no contact chaos grown from it
            np.testing.assert_allclose(np.array(b[key], float), np.array(a[key], float), rtol=1e-10, atol=1e-12,
                                       err_msg=f"{c} {key}")
        b = split.per_trial[c]
        assert a["success"] == b["success"] and a["extracted"] == b["extracted"]
        # a batch of another size can still stop MuJoCo's solver at another iteration (docs/panda.md, "The same
        # numbers across workers and threads"): round-off, grown by contact (an insertion time is a multiple of
        # the 10 ms period)
        np.testing.assert_allclose(np.array(b["insertion_time"], float), np.array(a["insertion_time"], float),
                                   atol=0.0101)
    assert base.summary["ik_fc"]["successes"] >= 1


def test_a_share_of_a_batch_sits_where_it_sits_in_the_whole_batch() -> None:
    from a3cqp_rl.robot.sim import grid_origins
    from envs.panda import PandaEnv

    env = PandaEnv(2, scene="peg_in_hole", grid=(5, [1, 4]))
    np.testing.assert_array_equal(env.sim._origin, grid_origins("peg_mesh", env.scene.mjcf(), 5)[[1, 4]])
    with pytest.raises(ValueError, match="grid places"):
        PandaEnv(2, scene="peg_in_hole", grid=(2, [1, 4]))
