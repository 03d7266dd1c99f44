"""PandaEnv: TorchRL specs, per-axis observation/action shapes, a point-mass policy unchanged, seeds, force sensing
(F/T, J^T† τ, f_ope), noise and bias, the operator model, divergence isolation, joint and torque limits."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch
from torchrl.envs.utils import check_env_specs

from a3cqp_rl.checkpoint import save_atomic
from a3cqp_rl.config import OperatorConfig, config_from_dict
from a3cqp_rl.exceptions import ConfigError
from a3cqp_rl.robot import PANDA_HOME, PANDA_LIMITS
from algorithms.a2c import load_policy
from algorithms.networks import ParamLayout
from envs.panda import PandaEnv, to_local
from envs.panda_eval import limit_stress
from envs.scenarios import Operator

# short procedures so that the tests reach contact quickly
FAST_PEG = {"panda": {"peg_in_hole": {"settle_time": 0.1, "approach_time": 1.0, "align_time": 3.0,
                                      "time_limit": 6.0}}}


def _cfg(extra: dict | None = None):  # noqa: ANN202
    d = {"panda": {**FAST_PEG["panda"]}}
    for k, v in (extra or {}).get("panda", {}).items():
        d["panda"][k] = {**d["panda"].get(k, {}), **v} if isinstance(v, dict) else v
    return config_from_dict(d)


def _ik_action(n: int) -> torch.Tensor:
    """Eq. 27 rates that keep IK on and everything else off (w̌ -> (+3, -3, -3), f_d -> 0)."""
    return torch.tensor([1.0, -1.0, -1.0, -1.0]).expand(n, 6, 4).clone()


@pytest.fixture(scope="module")
def policy_file(tmp_path_factory) -> str:  # noqa: ANN001
    """A point-mass-format policy.pt (random weights: obs [..., 3] -> action [..., 4])."""
    layout = ParamLayout(3, 4, (64, 64), "separate")
    flat = layout.init(torch.Generator().manual_seed(0), 0.0)
    path = tmp_path_factory.mktemp("pol") / "policy.pt"
    save_atomic({"format": 1, "flat": flat, "layout": [3, 4, [64, 64], "separate", 3]}, path)
    return str(path)


def test_check_env_specs_and_shapes() -> None:
    env = PandaEnv(2, _cfg(), seed=0)
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].shape == (2, 6, 3) and td["observation"].dtype == torch.float32
    assert env.action_spec.shape == (2, 6, 4)
    td["action"] = env.action_spec.rand()
    out = env.step(td)["next"]
    assert out["reward"].shape == (2, 6, 1)
    assert out["done"].shape == (2, 1)
    assert (out["observation"] >= 0).all() and (out["observation"] <= 1).all()
    for k in ("e_local", "f_env_local", "f_ope_local", "weights", "f_d", "phase", "misalign_translation", "depth"):
        assert k in out.keys()
    w = out["weights"]
    assert torch.allclose(w.sum(-1), torch.ones(2, 6, dtype=w.dtype))


def test_point_mass_policy_runs_unchanged_and_sets_weights_per_axis(policy_file: str) -> None:
    policy = load_policy(policy_file)
    env = PandaEnv(2, _cfg(), seed=1)
    td = env.reset()
    for _ in range(30):
        td["action"] = policy(td["observation"])  # [2, 6, 3] -> [2, 6, 4]: the six agents share one policy
        td = env.step(td)["next"]
    assert td["weights"].shape == (2, 6, 3)
    assert not env.diverged.any()
    # the desired torques are zero; f_d only on the translational axes
    assert (env.f_d[:, 3:] == 0).all()


def test_fd_axes_restricts_the_desired_force() -> None:
    env = PandaEnv(1, _cfg({"panda": {"fd_axes": ["z"]}}), seed=0)
    td = env.reset()
    td["action"] = torch.ones(1, 6, 4)  # push every f_d up
    env.step(td)
    assert env.f_d[0, 2] > 0 and (env.f_d[0, [0, 1, 3, 4, 5]] == 0).all()


def test_a_pull_on_an_fd_axis_reads_as_no_wall_unless_observed() -> None:
    """eq. 26 observes |f_env|; the surrogate's wall only pushes back (f_env^L ≤ 0 along the axis f_d pushes on), so with
    `observe_f_env_pull: false` a pull there reads 0; a push, the other axes and the recorded wrench are unchanged."""
    e, fo = torch.zeros(1, 6, dtype=torch.float64), torch.zeros(1, 6, dtype=torch.float64)
    fe = torch.tensor([[6.0, -6.0, 7.0, 0.3, 0.0, 0.0]], dtype=torch.float64)  # x and z pull, y pushes
    masked = PandaEnv(1, _cfg({"panda": {"fd_axes": ["y", "z"], "observe_f_env_pull": False}}), seed=0)
    kept = PandaEnv(1, _cfg({"panda": {"fd_axes": ["y", "z"]}}), seed=0)
    assert kept.pcfg.observe_f_env_pull  # the dataclass default: the sensed wrench as it is
    obs_m, obs_k = masked._observation(e, fe, fo), kept._observation(e, fe, fo)
    assert obs_m[0, 2, 1] == 0.0 and obs_k[0, 2, 1] == pytest.approx(7.0 / 30.0)  # z: an f_d axis, pulled
    assert obs_m[0, 0, 1] == obs_k[0, 0, 1] > 0.0  # x: no f_d, so no wall side: kept
    assert obs_m[0, 1, 1] == obs_k[0, 1, 1] > 0.0  # y: pushed back, as by a wall
    assert obs_m[0, 3, 1] == obs_k[0, 3, 1] > 0.0  # a torque: kept
    assert fe[0, 2] == 7.0  # the caller's wrench is not written to
    pushed = fe.clone()
    pushed[0, 2] = -7.0
    assert masked._observation(e, pushed, fo)[0, 2, 1] == pytest.approx(7.0 / 30.0)


def test_the_solver_warm_start_is_off_unless_the_config_asks_for_it() -> None:
    import mujoco

    from a3cqp_rl.config import ConfigError

    warm = int(mujoco.mjtDisableBit.mjDSBL_WARMSTART)
    for value, off in ((None, True), (False, True), (True, False)):
        extra = {} if value is None else {"panda": {"solver_warmstart": value}}
        for threads in (1, 2):
            env = PandaEnv(2, _cfg(extra), seed=0, sim_threads=threads)
            assert all(bool(m.opt.disableflags & warm) == off for m in env.sim.models), (value, threads)
            assert all(m.opt.jacobian == mujoco.mjtJacobian.mjJAC_SPARSE for m in env.sim.models)
    with pytest.raises(ConfigError, match="solver_warmstart"):
        _cfg({"panda": {"solver_warmstart": "maybe"}})


def test_the_contact_prefilter_is_on_unless_the_config_switches_it_off() -> None:
    from a3cqp_rl.config import ConfigError
    from a3cqp_rl.robot import contact_filter

    built = contact_filter._library.get() is not None
    for value, on in ((None, built), (True, built), (False, False)):
        extra = {} if value is None else {"panda": {"contact_prefilter": value}}
        for threads in (1, 2):
            env = PandaEnv(2, _cfg(extra), seed=0, sim_threads=threads)
            assert env.sim.contact_prefilter == on, (value, threads)
    with pytest.raises(ConfigError, match="contact_prefilter"):
        _cfg({"panda": {"contact_prefilter": "yes please"}})


def test_the_scenes_task_reward_is_added_to_eq_30_on_every_axis() -> None:
    rewards = []
    for cost in (0.0, 2.5):
        env = PandaEnv(2, _cfg({"panda": {"peg_in_hole": {"time_cost": cost}}}), seed=3)
        td = env.reset()
        td["action"] = _ik_action(2)
        env.scene.phase[:] = env.scene.INSERT  # arm 0 inserting since its first contact, arm 1 before contact
        env.scene.contact_time[0, 0] = 0.0
        rewards.append(env.step(td)["next", "reward"])
    assert rewards[0].shape == (2, 6, 1)
    assert torch.equal(rewards[1][0], rewards[0][0] - 2.5) and torch.equal(rewards[1][1], rewards[0][1])


def test_same_seed_same_numbers_and_trial_seeds_share_trials() -> None:
    runs = []
    for _ in range(2):
        env = PandaEnv(2, _cfg(), seed=7)
        td = env.reset()
        for _ in range(20):
            td["action"] = _ik_action(2)
            td = env.step(td)["next"]
        runs.append((env.q.copy(), env.scene.offset.copy()))
    assert np.array_equal(runs[0][0], runs[1][0]) and np.array_equal(runs[0][1], runs[1][1])
    other = PandaEnv(2, _cfg(), seed=8)
    assert not np.allclose(other.scene.offset, runs[0][1])
    env = PandaEnv(3, _cfg(), trial_seeds=[5, 6, 5])
    assert np.array_equal(env.scene.offset[0], env.scene.offset[2])
    assert not np.allclose(env.scene.offset[0], env.scene.offset[1])


def test_set_seed_goes_on_to_the_trials_construction_with_that_seed_does() -> None:
    """`PandaEnv(n, seed=s)` then a rollout, and `env.set_seed(s)` on another env then a rollout: the same trials and
    numbers (construction draws its arms' first trial; set_seed used to leave it to the rollout's reset)."""
    def rollout(env: PandaEnv) -> tuple[torch.Tensor, np.ndarray]:
        obs = env.rollout(8, policy=lambda td: td.set("action", _ik_action(2)))["next", "observation"]
        return obs, env.scene.offset.copy()  # (the trial's misalignment)

    a = rollout(PandaEnv(2, _cfg(), seed=0))
    other = PandaEnv(2, _cfg(), seed=5)
    other.set_seed(0)
    b = rollout(other)
    assert torch.equal(b[0], a[0]) and np.array_equal(b[1], a[1])
    assert not np.array_equal(rollout(PandaEnv(2, _cfg(), seed=5))[1], a[1])


def test_resetting_one_arm_leaves_the_others_bit_for_bit() -> None:
    """A partial reset reads every arm's sensors again (mj_step1); the arms it does not name keep what their last
    control period measured, so their trajectories equal a run without the reset (it used to move them by 1e-14 to
    3e-3 rad over an episode through the next step's reference rules)."""
    gen = torch.Generator().manual_seed(3)
    actions = [torch.rand(2, 6, 4, generator=gen) * 2.0 - 1.0 for _ in range(40)]
    qs = []
    for reset_at in (None, 15):
        env = PandaEnv(2, _cfg(), trial_seeds=[3, 4])
        td = env.reset()
        for k, a in enumerate(actions):
            if k == reset_at:
                td = env.reset(td.empty().set("_reset", torch.tensor([[True], [False]])))
            td["action"] = a
            td = env.step(td)["next"]
        qs.append((env.q.copy(), env.qd.copy(), env.weights.copy()))
    assert all(np.array_equal(a[1], b[1]) for a, b in zip(*qs))
    assert not np.array_equal(qs[0][0][0], qs[1][0][0])  # arm 0 did start again


def test_force_sensing_separates_operator_and_contact() -> None:
    # guidance: no contact, the operator pushes at the handle (above the F/T sensor)
    env = PandaEnv(1, _cfg({"panda": {"guidance": {"pause": 0.2}, "operator": {"noise": 0.0}}}), seed=0,
                   scene="guidance")
    td = env.reset()
    seen = []
    for _ in range(120):
        td["action"] = _ik_action(1)
        td = env.step(td)["next"]
        if env.operator.active[0]:
            seen.append((env.f_ope[0, :3].copy(), env.f_env[0, :3].copy(), env.handle_force[0].copy()))
    f_ope, f_env, hand = (np.array(x) for x in zip(*seen))
    assert np.abs(hand).max() > 5.0  # the hand really pushed
    assert np.abs(f_env).max() < 0.05  # nothing below the sensor is touched
    # f_ope = J^T† τ - f_env recovers the hand force (applied one control period before it is sensed)
    assert np.abs(f_ope - hand).max() < 0.3 * np.abs(hand).max()
    # peg-in-hole: contact below the sensor, no operator; per control period: the F/T-based f_env is the contact
    # force MuJoCo applied to the peg in the previous period, and f_ope stays ~0
    env = PandaEnv(1, _cfg(), seed=0)
    td = env.reset()
    tick, rec = env._tick, []

    def recording_tick(*a):  # noqa: ANN002, ANN202
        bad = tick(*a)
        rec.append((env.f_env[0, :3].copy(), env.f_ope[0, :3].copy(), env.sim.contact_force("peg")[0]))
        return bad

    env._tick = recording_tick
    while env.t[0] < 4.0:
        td["action"] = _ik_action(1)
        td = env.step(td)["next"]
    f_env, f_ope, contact = (np.array(x) for x in zip(*rec))
    touching = np.linalg.norm(contact[:-1], axis=1) > 1.0
    assert touching.sum() > 500
    # (to a few mN: the tool's rotational inertia is neglected when its inertial force is removed)
    np.testing.assert_allclose(f_env[1:][touching], contact[:-1][touching], atol=0.02, rtol=1e-3)
    assert np.abs(f_ope[1:][touching]).max() < 0.1 * np.abs(contact).max()
    # local frame: D^T
    R = env.rot[0]
    assert np.allclose(to_local(env.rot, env.f_env)[0, :3], R.T @ env.f_env[0, :3])


def test_sensor_noise_and_bias_are_configurable_and_off_by_default() -> None:
    quiet = PandaEnv(1, _cfg(), seed=0)
    noisy = PandaEnv(1, _cfg({"panda": {"sensors": {"ft_force_noise": 0.5, "ft_force_bias": 2.0}}}), seed=0)
    samples = {}
    for name, env in (("quiet", quiet), ("noisy", noisy)):
        td = env.reset()
        f = []
        for _ in range(40):
            td["action"] = _ik_action(1)
            td = env.step(td)["next"]
            f.append(env.f_env[0, :3].copy())
        samples[name] = np.array(f)
    assert np.abs(samples["quiet"]).max() < 0.05
    dev = samples["noisy"] - samples["noisy"].mean(0)
    assert 0.3 < dev.std() < 0.7  # ~0.5 N per component
    assert np.linalg.norm(samples["noisy"].mean(0)) > 0.3  # the per-episode bias
    assert np.allclose(noisy._ft_bias[0, 3:], 0.0)


def test_taring_removes_the_sensor_bias_and_the_readings_are_zero_until_then() -> None:
    """Biased F/T and joint torque sensors tared over the first 0.2 s at rest read what unbiased ones read (the rest
    pose's tiny true reading is zeroed too); before that they read zero; a second episode is tared again."""
    bias = {"ft_force_bias": 1.0, "ft_torque_bias": 0.1, "joint_torque_bias": 0.2}

    def readings(sensors: dict, episodes: int = 1) -> list:
        env = PandaEnv(2, _cfg({"panda": {"sensors": sensors, "peg_in_hole": {"settle_time": 0.3}}}), seed=4)
        out = []
        for _ in range(episodes):
            td = env.reset()
            for _ in range(30):
                td["action"] = _ik_action(2)
                td = env.step(td)["next"]
                out.append((env.t[0], env.f_env.copy(), env.f_ext.copy(), env.f_ope.copy()))
        return out

    clean, biased = readings({}), readings(bias)
    tared = readings({**bias, "tare_time": 0.2}, episodes=2)
    assert max(np.abs(b[3]).max() for b in biased) > 1.0  # the bias alone reads as an operator's push
    for (t, *c), (_, *r) in zip(clean * 2, tared):
        if t < 0.2 - 1e-9:
            assert all(np.array_equal(x, np.zeros_like(x)) for x in r), t
        else:
            assert all(np.abs(x - y).max() < 1e-4 for x, y in zip(c, r)), t
    with pytest.raises(ValueError, match="tare_time"):
        PandaEnv(1, _cfg({"panda": {"sensors": {"tare_time": 0.2}}}))  # the tests' settle_time: 0.1 s


def test_the_scene_reads_the_true_contact_wrench_not_the_noisy_sensor() -> None:
    """In the air, F/T noise of 2 N per sample passes the peg's 1 N first-contact threshold, but the insertion's
    first contact (and so its time) is the simulation's: none yet."""
    env = PandaEnv(2, _cfg({"panda": {"sensors": {"ft_force_noise": 2.0}}}), seed=1)
    td = env.reset()
    env.scene.phase[:] = env.scene.INSERT  # the insertion reference from the start: the peg is still in the air
    sensed = 0.0
    for _ in range(5):
        td["action"] = _ik_action(2)
        td = env.step(td)["next"]
        sensed = max(sensed, np.linalg.norm(env.f_env[:, :3], axis=1).max())
        assert np.abs(env.f_env_true).max() < 0.01  # the F/T compensation neglects the tool's rotational inertia
    assert sensed > env.scene.cfg.contact_force
    assert np.isnan(env.scene.contact_time).all()


def test_operator_is_bounded_delayed_and_releases() -> None:
    cfg = OperatorConfig(stiffness=400.0, max_force=15.0, delay=0.05, noise=0.0, hold_time=0.1, grip_time=0.01)
    op = Operator(1, cfg, 0.001)
    t = np.zeros(1)
    pos, rot = np.zeros((1, 3)), np.eye(3)[None]
    op.update(t, pos, rot)
    op.grasp(np.array([0]), np.array([[1.0, 0.0, 0.0]]), t)
    forces = []
    for k in range(300):
        t = np.array([k * 0.001])
        moved = pos + (np.array([[0.0, 0.5, 0.0]]) if k >= 100 else 0.0)  # the handle jumps sideways at 100 ms
        f, _ = op.wrench(t, moved, np.zeros((1, 3)), rot, np.zeros((1, 3)))
        forces.append(f[0].copy())
    forces = np.array(forces)
    assert np.linalg.norm(forces, axis=1).max() <= 15.0 + 1e-9
    assert np.abs(forces[100:149, 1]).max() < 1e-9  # the hand has not seen the jump yet (50 ms delay)
    assert forces[160, 1] < -10.0  # now it pulls back
    # reached the goal -> holds for hold_time -> releases
    for k in range(200):
        t = np.array([0.3 + k * 0.001])
        op.update(t, np.array([[1.0, 0.0, 0.0]]), rot)
    assert not op.active[0] and op.releases[0] == 1 and op.reached[0]


def test_with_a_release_speed_the_hand_lets_go_of_a_reached_goal_only_once_the_handle_is_still() -> None:
    cfg = OperatorConfig(noise=0.0, hold_time=0.1, grip_time=0.01, goal_tolerance=0.01, release_speed=0.05,
                         timeout=3.0)
    op, rot, goal = Operator(2, cfg, 0.001), np.tile(np.eye(3), (2, 1, 1)), np.array([[1.0, 0.0, 0.0]] * 2)
    op.update(np.zeros(2), np.zeros((2, 3)), rot)
    op.grasp(np.arange(2), goal, np.zeros(2))
    # both handles reach the goal at 1 s; arm 0 stops there, arm 1 swings through it at 0.2 m/s for 1 s
    for k in range(100, 200):
        op.update(np.full(2, k * 0.01), np.array([[1.0, 0.0, 0.0], [1.0 + 0.002 * (k % 2), 0.0, 0.0]]), rot)
        if k == 115:  # hold_time passed: the still arm is let go of, the swinging one is not
            assert op.state.tolist() == [Operator.IDLE, Operator.HOLD] and op.releases.tolist() == [1, 0]
    assert op.state[1] == Operator.HOLD
    op.update(np.full(2, 2.0), np.array([[1.0, 0.0, 0.0]] * 2), rot)  # a step of 0.002 m in 0.01 s: still moving
    op.update(np.full(2, 2.01), np.array([[1.0, 0.0, 0.0]] * 2), rot)  # now still
    assert op.state[1] == Operator.RELEASE
    # the timeout lets go whatever the handle's speed
    op.grasp(np.arange(2), goal, np.full(2, 3.0))
    for k in range(301):
        op.update(np.full(2, 3.0 + k * 0.01), np.array([[1.0 + 0.002 * (k % 2), 0.0, 0.0]] * 2), rot)
    assert (op.state != Operator.HOLD).all()


@pytest.fixture
def mujoco_warnings():  # noqa: ANN201
    """MuJoCo's warnings collected in a list instead of its MUJOCO_LOG.TXT in the working directory."""
    import mujoco

    seen: list[str] = []
    mujoco.set_mju_user_warning(seen.append)
    yield seen
    mujoco.set_mju_user_warning(None)


def test_a_diverging_robot_ends_its_own_episode_only(caplog, mujoco_warnings) -> None:  # noqa: ANN001
    ref = PandaEnv(3, _cfg(), seed=2)
    env = PandaEnv(3, _cfg(), seed=2)
    tds = [ref.reset(), env.reset()]
    for k in range(40):
        for i, e in enumerate((ref, env)):
            tds[i]["action"] = _ik_action(3)
            tds[i] = e.step(tds[i])["next"]
        if k == 10:
            dof = env.sim.model.jnt_dofadr[env.sim.model.joint("arm1/joint4").id]
            env.sim.data.qvel[dof] = np.nan  # a simulation blow-up in robot 1 only
            caplog.set_level(logging.WARNING)
        if k == 11:
            assert bool(tds[1]["terminated"][1]) and bool(tds[1]["diverged"][1])
            assert not tds[1]["done"][[0, 2]].any()
    assert sum("robot 1 diverged" in r.message for r in caplog.records) == 1
    assert any("unstable" in w for w in mujoco_warnings)  # MuJoCo saw it too, and did not reset the batch
    assert env.diverged.tolist() == [False, True, False]
    # the other robots did not notice (MuJoCo's own auto-reset of the whole batch is off)
    np.testing.assert_allclose(env.q[[0, 2]], ref.q[[0, 2]], atol=1e-9)
    assert np.isfinite(env.q).all()
    td = env.reset(tds[1].empty().set("_reset", torch.tensor([[False], [True], [False]])))
    assert not env.diverged.any() and bool(torch.isfinite(td["observation"]).all())


def _random_episodes(n: int, steps: int, seed: int) -> tuple[float, float, int]:
    """Random actions (held 0.2 s) on peg-in-hole with operator episodes; (max joint-limit violation [rad], max
    |τ|/τ_max, diverged robots)."""
    r = limit_stress(n, steps, seed, _cfg({"panda": {"peg_in_hole": {"time_limit": 3.0}}}))
    return r.worst_excess, r.worst_torque_ratio, r.diverged


def test_joint_and_torque_limits_hold_under_random_actions() -> None:
    worst_q, worst_tau, diverged = _random_episodes(4, 400, seed=0)
    assert worst_q < 0.0 and worst_tau <= 1.0 + 1e-12 and diverged == 0


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_joint_and_torque_limits_hold_over_many_random_episodes(seed: int) -> None:
    """Torques never exceed their limits, and the joints stay within 8 mrad of theirs. A joint can reach its end stop:
    under random weights the tool is dragged along a surface and the contact's impulses drive joint 6 into it, past
    anything the wrist's 12 N m can brake (docs/panda.md, "Joint limits under random weights"). The joint ranges are
    stiff end stops (panda.xml, solreflimit 2 ms), which hold it 0.3-5.6 mrad deep on seeds 1-12 (two above 5 mrad,
    where the peg struck at 2.3-2.6x joint 6's speed limit); MuJoCo's default 20-ms stop let it 9-41 mrad deep
    (docs/panda.md, "Stiff end stops", "A failed trial ends at its time limit"). Without external force no joint
    reaches its limit (test_without_external_force_random_actions_never_pass_a_joint_limit)."""
    worst_q, worst_tau, diverged = _random_episodes(8, 3000, seed=seed)
    assert worst_q < 0.008 and worst_tau <= 1.0 + 1e-12 and diverged == 0


NO_EXTERNAL_FORCE = {"panda": {"scene": "guidance", "operator": {"max_force": 1e-6, "max_torque": 1e-6}}}
"""Free space (the guidance scene has no obstacle) with the operator's wrench bounded at 1 µN, 1 µN m."""


def test_without_external_force_random_actions_never_pass_a_joint_limit() -> None:
    """With no external force on the arm the viable bounds keep every joint inside its limits under random weights
    (a joint reaches the controller's bound, 10 mrad inside the limit; seeds 1, 2, 3, 5 with 8 arms x 3000 steps:
    never past a limit either); the excess of the test above comes from
    the operator's and the contacts' forces (docs/panda.md, "External forces carry the joints past their limits")."""
    r = limit_stress(4, 1500, 2, _cfg(NO_EXTERNAL_FORCE))
    assert -0.02 < r.worst_excess, "no joint came near its limit: the check would not be one"
    assert r.worst_excess < 0.0 and r.worst_torque_ratio <= 1.0 + 1e-12 and r.diverged == 0 and r.fallbacks == 0
    assert 0.9 < r.worst_speed_ratio <= 1.0  # a joint reaches its speed bound (2 % inside the limit), none passes it


@pytest.mark.slow
@pytest.mark.parametrize("seed", [1, 2, 3])
def test_counting_the_measured_wrench_holds_the_joint_limits_against_the_operator(seed: int) -> None:
    """In the guidance scene (the operator guides, no contact) `panda.joint_limits_f_ext` (its config's default)
    keeps every joint inside its limits under random weights, without a QP fallback; without it the operator's pull
    carries joint 6 into its end stop on these seeds, 1.6-1.8 mrad deep (10-17 mrad into MuJoCo's default soft stop;
    docs/panda.md)."""
    cfg = _cfg({"panda": {"scene": "guidance", "joint_limits_f_ext": "always"}})
    r = limit_stress(8, 3000, seed, cfg)
    assert r.worst_excess < 0.0 and r.worst_torque_ratio <= 1.0 + 1e-12 and r.diverged == 0 and r.fallbacks == 0


def test_joint_limit_excess_is_tracked_per_arm_over_the_episode() -> None:
    env = PandaEnv(2, _cfg(), seed=0)
    td = env.reset()
    assert np.all(env.joint_limit_excess == -np.inf)
    td["action"] = _ik_action(2)
    td = env.step(td)["next"]
    home = env.joint_limit_excess.copy()
    assert np.all((-1.0 < home) & (home < 0.0))  # inside the limits at home: the closest approach, negative
    m, q_hi = env.sim.model, np.array(PANDA_LIMITS.q_max)
    adr = m.jnt_qposadr[m.joint("arm1/joint4").id]
    env.sim.data.qpos[adr] = q_hi[3] + 0.02  # arm 1's joint 4 pushed 20 mrad past its datasheet limit
    td["action"] = _ik_action(2)
    td = env.step(td)["next"]
    assert 0.019 < env.joint_limit_excess[1] <= 0.02 + 1e-9  # seen at the first control period
    assert env.joint_limit_joint[1] == 3
    assert env.joint_limit_excess[0] == home[0]
    assert 0.0 <= env.joint_speed_ratio[0] < 1.0  # (arm 1's joint 4 is thrown back out by its stiff end stop)
    speed0 = env.joint_speed_ratio[0]
    env.sim.data.qvel[m.jnt_dofadr[m.joint("arm0/joint6").id]] = 1.5 * PANDA_LIMITS.dq_max[5]  # arm 0's wrist too fast
    td["action"] = _ik_action(2)
    td = env.step(td)["next"]
    assert env.joint_speed_ratio[0] > 1.2
    env.park(np.array([1]))  # a parked arm's motion no longer counts
    env.sim.data.qpos[adr] = q_hi[3] + 0.05
    td["action"] = _ik_action(2)
    env.step(td)
    assert env.joint_limit_excess[1] <= 0.02 + 1e-9
    kept = env.joint_limit_excess[0]
    env.reset(td.empty().set("_reset", torch.tensor([[False], [True]])))
    assert env.joint_limit_excess[1] == -np.inf and env.joint_limit_excess[0] == kept >= home[0]
    assert env.joint_speed_ratio[1] == 0.0 and env.joint_speed_ratio[0] > 1.2 > speed0
    assert env.joint_limit_joint[1] == -1 and env.joint_limit_joint[0] >= 0


def test_joint_limits_f_ext_turns_on_the_controllers_option(monkeypatch) -> None:  # noqa: ANN001
    assert not PandaEnv(1, _cfg(), seed=0).ctrl.options.joint_limits_include_f_ext
    env = PandaEnv(1, _cfg({"panda": {"joint_limits_f_ext": "always"}}), seed=0)
    assert env.ctrl.options.joint_limits_include_f_ext
    from a3cqp_rl.config import load_config
    from a3cqp_rl.exceptions import ConfigError
    assert load_config("configs/panda_guidance.yaml").panda.joint_limits_f_ext == "always"
    assert load_config("configs/panda_peg_in_hole.yaml").panda.joint_limits_f_ext == "operator"
    assert load_config("configs/panda_polishing.yaml").panda.joint_limits_f_ext == "off"
    with pytest.raises(ConfigError, match="joint_limits_f_ext"):
        _cfg({"panda": {"joint_limits_f_ext": True}})
    # "operator": the arms the operator holds, step by step (the controller's option stays off)
    env = PandaEnv(2, _cfg({"panda": {"joint_limits_f_ext": "operator"}}), seed=0)
    assert not env.ctrl.options.joint_limits_include_f_ext
    seen = []
    step = env.ctrl.step
    monkeypatch.setattr(env.ctrl, "step", lambda *a, **k: seen.append(k["f_ext_limits"].clone()) or step(*a, **k))
    td = env.reset()
    env.operator.grasp(np.array([1]), env.handle_pos[[1]], env.t)
    td["action"] = _ik_action(2)
    env.step(td)
    assert len(seen) == env.substeps and all(m.tolist() == [False, True] for m in seen)


def test_axis_agents_view_trains_one_shared_policy_with_a2c(tmp_path) -> None:  # noqa: ANN001
    from a3cqp_rl.config import load_config
    from algorithms.a2c import train
    from envs.panda import PandaAxisAgents

    env = PandaAxisAgents(2, _cfg(), seed=0)
    check_env_specs(env)
    td = env.reset()
    assert td["observation"].shape == (12, 3)
    td["action"] = torch.zeros(12, 4)
    out = env.step(td)["next"]
    assert out["reward"].shape == (12, 1) and out["done"].shape == (12, 1)
    # a reset names an arm's six agents (the arm resets as a whole), not some of them: TorchRL would keep the others'
    # old observations
    env.inner.t[:] = 5.0
    with pytest.raises(ValueError, match=r"only some of the six agents of arm\(s\) \[1\]"):
        env.reset(out.empty().set("_reset", torch.tensor([[False]] * 6 + [[True]] + [[False]] * 5)))
    assert env.inner.t.tolist() == [5.0, 5.0]
    back = env.reset(out.clone().set("_reset", torch.tensor([[False]] * 6 + [[True]] * 6)))
    assert env.inner.t.tolist() == [5.0, 0.0]
    fresh = env.inner._observation(*[torch.from_numpy(a) for a in env.inner.local_state()])
    assert torch.equal(back["observation"][6:], fresh.reshape(12, 3)[6:].to(torch.float32))
    cfg = load_config("configs/panda_a2c.yaml", {"a2c": {"num_envs": 1, "n_steps": 4, "compile": False,
                                                          "region_checks": 0}})
    res = train(cfg, tmp_path / "run", total_steps=240)
    assert res.steps == 240 and load_policy(res.policy_path)(torch.zeros(6, 3)).shape == (6, 4)


def test_torchrls_gae_gives_the_arms_and_the_axis_agents_the_same_advantages() -> None:
    from tensordict.nn import TensorDictModule
    from torchrl.objectives.value import GAE

    from envs.panda import PandaAxisAgents, agent_done_flags

    torch.manual_seed(0)
    value = TensorDictModule(torch.nn.Sequential(torch.nn.Linear(3, 8), torch.nn.Tanh(), torch.nn.Linear(8, 1)),
                             in_keys=["observation"], out_keys=["state_value"])
    gae = GAE(gamma=0.9, lmbda=0.8, value_network=value)
    steps, cfg = 6, _cfg({"panda": {"max_episode_time": 0.04}})  # 4 agent steps: an episode ends inside

    def act(td):  # noqa: ANN001, ANN202
        return td.set("action", torch.full((*td["observation"].shape[:-1], 4), 0.3))

    flat = gae(PandaAxisAgents(2, cfg, seed=0).rollout(steps, act, break_when_any_done=False))
    arms = PandaEnv(2, cfg, seed=0).rollout(steps, act, break_when_any_done=False)
    with pytest.raises(RuntimeError, match="share a unique shape"):
        gae(arms.clone())  # TorchRL's own error: one done per arm, one reward per agent
    gae.set_keys(done="agent_done", terminated="agent_terminated")
    arms = gae(agent_done_flags(arms))
    assert arms["next", "agent_done"].shape == (2, steps, 6, 1) and arms["next", "done"].any()
    assert torch.allclose(arms["advantage"].transpose(1, 2).reshape(12, steps, 1), flat["advantage"], atol=1e-6)


def _steps_held(env: PandaEnv, steps: int):  # noqa: ANN201
    """Step a one-arm env `steps` agent periods with w = (0, 0.5, 0.5) and f_d = 0 held on every axis (the weights
    the point-mass policy leaves after guiding), yielding after each step."""
    w, f_d = np.tile([0.0, 0.5, 0.5], (1, 6, 1)), np.zeros((1, 6))
    td = env._output(done=np.zeros(1, dtype=bool), terminated=np.zeros(1, dtype=bool))
    for _ in range(steps):
        env.hold_weights(np.ones(1, dtype=bool), w, f_d)
        td["action"] = torch.zeros(1, 6, 4)
        td = env.step(td)["next"]
        yield


def _coast(idle_force: str) -> float:
    """Largest tool displacement [m] in 0.5 s after the arm is let go at ~0.1 m/s with the weights the point-mass
    policy leaves after guiding, w = (0, 0.5, 0.5) and f_d = 0 on every axis (no operator, no contact)."""
    env = PandaEnv(1, _cfg({"panda": {"scene": "guidance", "idle_force": idle_force}}), seed=0)
    env.reset()
    q0 = np.array([PANDA_HOME])
    qd0 = np.array([[0.0, 0.15, 0.0, -0.15, 0.0, 0.0, 0.0]])
    env.sim.reset(q0, qd0, idx=[0])
    env.ctrl.reset(torch.tensor(q0), torch.tensor(qd0), idx=torch.tensor([0]))
    env._measure()
    start, drift = env.pos[0].copy(), 0.0
    for _ in _steps_held(env, 50):
        drift = max(drift, float(np.linalg.norm(env.pos[0] - start)))
    return drift


def test_force_control_that_does_not_push_damps_instead_of_letting_the_arm_coast() -> None:
    # eq. 35 as is: w3 with f_d = 0 commands nothing, only w2's admittance damping (Cd/Λd = 1/s) slows the arm
    free, damps = _coast("free"), _coast("damps")
    assert free > 0.03
    assert damps < 0.4 * free and damps < 0.015


def test_idle_share_relaxes_the_integral_only_where_a_non_ik_task_leads() -> None:
    env = PandaEnv(3, _cfg({"panda": {"scene": "guidance"}}), seed=0)
    env.reset()
    # arm 0: the operator's admittance leads (a relocation); arm 1: IK leads, FC idle (across the hole); arm 2: FC
    # pushes (no idle share)
    env.weights = np.stack([np.tile(w, (6, 1)) for w in ((0.0, 0.5, 0.5), (0.5, 0.0, 0.5), (0.2, 0.2, 0.6))])
    env.f_d = np.array([[0.0] * 6, [0.0] * 6, [5.0] * 6])
    w_ctrl, _ = env.controller_weights()
    rate = env.idle_share_leak(w_ctrl)
    leak = env.ctrl.options.desired_state_leak
    # arm 0: a / (w1 + a) = 1 in all, the controller's own leak gives w2 = 0.5 of it
    np.testing.assert_allclose(rate[0], 0.5 * leak)
    np.testing.assert_allclose(rate[1:], 0.0)
    free = PandaEnv(1, _cfg({"panda": {"scene": "guidance", "idle_force": "free"}}), seed=0)
    free.weights, free.f_d = env.weights[:1], env.f_d[:1]
    assert free.idle_share_leak(free.controller_weights()[0]) is None


def test_the_idle_share_rate_goes_to_the_controllers_per_axis_leak() -> None:
    env = PandaEnv(1, _cfg({"panda": {"scene": "guidance", "idle_force": "damps"}}), seed=0)
    env.reset()
    seen, step = [], env.ctrl.step
    env.ctrl.step = lambda *a, **k: seen.append(k.get("leak_extra")) or step(*a, **k)
    for _ in _steps_held(env, 2):
        pass
    assert len(seen) == 2 * env.substeps
    # w = (0, 0.5, 0.5), f_d = 0: the controller relaxes at 0.5 × leak, the share at the other half (1/s)
    leak = env.ctrl.options.desired_state_leak
    assert all(e is not None and np.allclose(e.numpy(), 0.5 * leak) for e in seen)


def _yield_to_push(relax: bool) -> float:
    """Tool travel [m] along world y under a 10 N push at the handle for 1 s, with w = (0, 0.5, 0.5), f_d = 0."""
    env = PandaEnv(1, _cfg({"panda": {"scene": "guidance", "idle_force": "damps"}}), seed=0)
    if not relax:
        env.idle_share_leak = lambda w_ctrl: None
    env.reset()
    env._measure()
    start = env.pos[0, 1]
    env.operator.wrench = lambda *args: (np.array([[0.0, 10.0, 0.0]]), np.zeros((1, 3)))
    env._hand = None  # (the C hand would not call the stand-in)
    for _ in _steps_held(env, 100):
        pass
    return float(env.pos[0, 1] - start)


def test_the_idle_share_damps_without_holding_a_position_against_the_operator() -> None:
    # without the relaxation, q* integrates the share's damping and pulls the arm back like a spring (in polishing the
    # operator's hand then stopped 11-12 mm short of its relocation goals)
    held, relaxed = _yield_to_push(False), _yield_to_push(True)
    assert held > 0.05
    assert relaxed > 1.1 * held


def test_held_weights_last_one_step():
    """hold_weights applies to the next step only: the step after it integrates the action again (eq. 29)."""
    env = PandaEnv(1, _cfg({"panda": {"scene": "guidance"}}), seed=0)
    td = env.reset()
    held = np.tile([0.2, 0.3, 0.5], (1, 6, 1))
    env.hold_weights(np.ones(1, dtype=bool), held, np.zeros((1, 6)))
    td["action"] = torch.zeros(1, 6, 4)
    td = env.step(td)["next"]
    np.testing.assert_allclose(env.weights, held)
    td["action"] = torch.tensor([[[1.0, 0.0, 0.0, 0.0]] * 6])  # raise the IK rate on every axis (eq. 29: +σw·Δt)
    env.step(td)
    assert (env.weights[..., 0] > held[..., 0] + 5e-3).all()


def _pressing(filter_: str) -> tuple[PandaEnv, list[np.ndarray], dict]:
    """A 2-arm peg env after 3 s of IK along the scene's approach; (env, the f_env samples of its last agent period,
    its output)."""
    env = PandaEnv(2, _cfg({"panda": {"observation_filter": filter_, "operator": {"noise": 0.0}}}), seed=3)
    td = env.reset()
    samples: list[np.ndarray] = []
    tick = env._tick

    def recording(k, *a, **kw):  # noqa: ANN001, ANN202
        out = tick(k, *a, **kw)
        samples.append(env.f_env.copy())
        return out

    env._tick = recording
    for _ in range(300):
        samples.clear()
        td["action"] = _ik_action(2)
        td = env.step(td)["next"]
    return env, samples, td


def test_observation_filter_mean_observes_the_agent_periods_mean_wrench() -> None:
    env, samples, td = _pressing("mean")
    assert len(samples) == env.substeps
    mean = np.mean(samples, axis=0)
    assert np.abs(mean - samples[-1]).max() > 1e-6  # the two filters differ on this period
    assert np.allclose(env.f_env_obs, mean, atol=1e-12)
    assert np.allclose(td["f_env_local"].numpy(), to_local(env.rot, mean), atol=1e-12)
    # "last" observes the period's last sample (the behaviour before the option)
    env, samples, td = _pressing("last")
    assert np.allclose(td["f_env_local"].numpy(), to_local(env.rot, samples[-1]), atol=1e-12)


def test_the_tool_axis_bound_moves_only_the_policy_arms_reference_along_the_tool_axis() -> None:
    from a3cqp_rl.config import ConfigError

    env = PandaEnv(3, _cfg({"panda": {"ik_bound_tool_axis": 0.02}}), seed=0)
    env.reset()
    axis = env.rot[:, :, 2]
    across = np.cross(axis, np.array([1.0, 0.0, 0.0]))
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    # 50 mm along the tool axis (arms 0, 2: toward the tool's front, arm 1: behind it) and 7 mm across it
    along = np.array([0.05, -0.05, 0.05])
    env.scene.pos_d[:] = env.pos + along[:, None] * axis + 0.007 * across
    env._scripted = np.array([False, False, True])  # arm 2's weights are held by a script this step
    pos_d, rot_d = (x.numpy() for x in env._controller_reference())
    e = pos_d - env.pos
    np.testing.assert_allclose(np.einsum("nk,nk->n", e, axis), [0.02, -0.02, 0.05], atol=1e-12)
    np.testing.assert_allclose(np.einsum("nk,nk->n", e, across), 0.007, atol=1e-12)  # across: untouched
    np.testing.assert_array_equal(rot_d, env.scene.rot_d)
    # within the bound, or without one, the reference is the scene's
    env.scene.pos_d[:] = env.pos + 0.015 * axis
    np.testing.assert_array_equal(env._controller_reference()[0].numpy(), env.scene.pos_d)
    free = PandaEnv(1, _cfg(), seed=0)
    free.reset()
    free.scene.pos_d[:] = free.pos + 0.05 * free.rot[:, :, 2]
    np.testing.assert_array_equal(free._controller_reference()[0].numpy(), free.scene.pos_d)
    for bad in (0.0, -0.01):
        with pytest.raises(ConfigError, match="ik_bound_tool_axis"):
            _cfg({"panda": {"ik_bound_tool_axis": bad}})
    # `ik_rules_scripted`: the scripted arm's reference is bounded as the policy arms' are
    every = PandaEnv(3, _cfg({"panda": {"ik_bound_tool_axis": 0.02, "ik_rules_scripted": True}}), seed=0)
    every.reset()
    axis = every.rot[:, :, 2]
    every.scene.pos_d[:] = every.pos + along[:, None] * axis
    every._scripted = np.array([False, False, True])
    e = every._controller_reference()[0].numpy() - every.pos
    np.testing.assert_allclose(np.einsum("nk,nk->n", e, axis), [0.02, -0.02, 0.02], atol=1e-12)


def test_in_contact_an_advancing_reference_is_not_left_behind_the_tool() -> None:
    """With the bound, a reference 5 mm (arms 0-3) or 50 mm (arm 4) behind the tool along its axis moves to the tool
    only for an arm in contact whose scene reference advanced along the axis (arms 0 and 4); not for one whose
    reference went back (arm 1, the return home), one without contact (arm 2) or one a script holds (arm 3)."""
    env = PandaEnv(5, _cfg({"panda": {"ik_bound_tool_axis": 0.02}}), seed=0)
    env.reset()
    np.testing.assert_array_equal(env._ref_step, 0.0)  # a fresh reference has not moved
    axis = env.rot[:, :, 2]
    along = np.array([-0.005, -0.005, -0.005, -0.005, -0.05])
    env.scene.pos_d[:] = env.pos + along[:, None] * axis + 0.003 * np.cross(axis, [1.0, 0.0, 0.0])
    env._ref_step[:] = np.array([1.0, -1.0, 1.0, 1.0, 1.0])[:, None] * 0.004 * axis
    env.f_env[:] = 0.0
    env.f_env[[0, 1, 3, 4], :3] = -5.0 * axis[[0, 1, 3, 4]]  # the block pushes the tool back along its axis
    env._scripted = np.array([False, False, False, True, False])
    e = env._controller_reference()[0].numpy() - env.pos
    np.testing.assert_allclose(np.einsum("nk,nk->n", e, axis), [0.0, -0.005, -0.005, -0.005, 0.0], atol=1e-12)
    env.scene.pos_d[:] = env.pos + 0.05 * axis  # ahead: the bound as before
    e = env._controller_reference()[0].numpy() - env.pos
    np.testing.assert_allclose(np.einsum("nk,nk->n", e, axis), [0.02, 0.02, 0.02, 0.05, 0.02], atol=1e-12)


def test_a_reference_that_moves_back_is_not_held_behind_the_tool() -> None:
    """A reference 50 mm behind the tool along its axis stays there where the tool is in contact and the scene's
    reference moved back along the axis (arms 0, 1: the return home pulls a peg the bore holds out); it is held 20 mm
    behind where the reference stood still (arm 2), moved across the axis only (arm 3) or the tool is free (arm 4)."""
    env = PandaEnv(5, _cfg({"panda": {"ik_bound_tool_axis": 0.02}}), seed=0)
    env.reset()
    axis = env.rot[:, :, 2]
    across = np.cross(axis, np.array([1.0, 0.0, 0.0]))
    across /= np.linalg.norm(across, axis=1, keepdims=True)
    env.scene.pos_d[:] = env.pos - 0.05 * axis
    env._ref_step[:] = 0.0
    env._ref_step[[0, 1, 4]] = -0.004 * axis[[0, 1, 4]]
    env._ref_step[3] = 0.004 * across[3]
    env.f_env[:] = 0.0
    env.f_env[:4, :3] = 8.0 * across[:4]  # the bore presses the tool sideways
    env.f_env[1, :3] = 8.0 * axis[1]  # the bore holds the peg: the block pulls the tool along its axis
    env._scripted = np.zeros(5, dtype=bool)
    e = env._controller_reference()[0].numpy() - env.pos
    np.testing.assert_allclose(np.einsum("nk,nk->n", e, axis), [-0.05, -0.05, -0.02, -0.02, -0.02], atol=1e-12)


def test_the_reference_step_is_the_scenes_last_move_along_the_procedure() -> None:
    """`_ref_step` follows the scene's reference from one agent step to the next (peg: the approach moves it)."""
    env = PandaEnv(2, _cfg({"panda": {"ik_bound_tool_axis": 0.02}}), seed=0)
    td = env.reset()
    for _ in range(80):  # past the settle time, into the approach
        before = env.scene.pos_d.copy()
        td["action"] = _ik_action(2)
        td = env.step(td)["next"]
        np.testing.assert_allclose(env._ref_step, env.scene.pos_d - before, atol=0.0)
    assert np.linalg.norm(env._ref_step, axis=1).min() > 0.0


def test_an_arm_left_unparked_after_its_episode_adds_nothing_to_its_counts() -> None:
    """Arm 0's scene is done (its episode over, the arm not parked): its joint-limit and joint-speed records and its
    fallback count stay as they were, while arm 1's go on."""
    env = PandaEnv(2, _cfg(), seed=0)
    td = env.reset()
    env.scene.done[0] = True
    env.joint_limit_excess[:], env.joint_speed_ratio[:] = -np.inf, 0.0
    for _ in range(3):
        td["action"] = _ik_action(2)
        td = env.step(td)["next"]
    assert env.joint_limit_excess[0] == -np.inf and env.joint_speed_ratio[0] == 0.0
    assert np.isfinite(env.joint_limit_excess[1]) and env.joint_speed_ratio[1] > 0.0
    np.testing.assert_array_equal(env._in_episode(), [False, True])
    env.park(np.array([1]))
    np.testing.assert_array_equal(env._in_episode(), [False, False])


def test_the_arms_a_script_holds_this_step_are_the_ones_left_unbounded() -> None:
    env = PandaEnv(2, _cfg({"panda": {"ik_bound_tool_axis": 0.02}}), seed=0)
    td = env.reset()
    env.hold_weights(np.array([False, True]), np.tile([1.0, 0.0, 0.0], (2, 6, 1)), np.zeros((2, 6)))
    td["action"] = _ik_action(2)
    td = env.step(td)["next"]
    np.testing.assert_array_equal(env._scripted, [False, True])
    td["action"] = _ik_action(2)
    env.step(td)  # the hold lasted one step
    np.testing.assert_array_equal(env._scripted, [False, False])


def test_a_blocked_tool_keeps_its_ik_reference_at_the_tool() -> None:
    """With `ik_bound_blocked` 0, a reference 15 mm ahead along the tool axis moves to the tool for a policy arm
    pressed back by more than `blocked_force` and still along its axis (arm 0); not for one pressed more lightly
    (arm 1), one moving along the axis (arm 2) or one a script holds (arm 3); the 20-mm bound holds arm 4 (50 mm)."""
    env = PandaEnv(5, _cfg({"panda": {"ik_bound_tool_axis": 0.02, "ik_bound_blocked": 0.0}}), seed=0)
    env.reset()
    axis = env.rot[:, :, 2]
    env.scene.pos_d[:] = env.pos + np.array([0.015, 0.015, 0.015, 0.015, 0.05])[:, None] * axis
    env._ref_step[:] = 0.0
    env.f_env[:] = 0.0
    env.f_env[:, :3] = -np.array([8.0, 3.0, 8.0, 8.0, 8.0])[:, None] * axis
    env._twist[:] = 0.0
    env._twist[2, :3] = 0.01 * axis[2]  # 10 mm/s along the axis
    env._scripted = np.array([False, False, False, True, False])
    e = env._controller_reference()[0].numpy() - env.pos
    np.testing.assert_allclose(np.einsum("nk,nk->n", e, axis), [0.0, 0.015, 0.015, 0.015, 0.0], atol=1e-12)


def test_a_sliding_tool_gets_its_reference_ahead_unless_it_is_blocked() -> None:
    """With `ik_lead_sliding` 10 mm, an arm in contact that slides forward along the tool axis (2 mm/s) while its scene
    reference advances gets a reference at least 10 mm ahead (arms 0, 1: 2 mm ahead, 5 mm behind), or farther where
    the scene's is (arm 5: 15 mm); not a pressed one within `blocked_speed` (arm 2: at the tool, blocked), one a
    script holds (arm 3), one without contact (arm 4) or one that does not slide (arm 6: 0.5 mm/s)."""
    cfg = {"panda": {"ik_bound_tool_axis": 0.02, "ik_bound_blocked": 0.0, "ik_lead_sliding": 0.01}}
    env = PandaEnv(7, _cfg(cfg), seed=0)
    env.reset()
    axis = env.rot[:, :, 2]
    along = np.array([0.002, -0.005, 0.002, 0.002, -0.005, 0.015, 0.002])
    env.scene.pos_d[:] = env.pos + along[:, None] * axis
    env._ref_step[:] = 0.004 * axis
    env.f_env[:] = 0.0
    env.f_env[:, :3] = -np.array([3.0, 3.0, 8.0, 3.0, 0.0, 3.0, 3.0])[:, None] * axis
    env._twist[:] = 0.0
    env._twist[:, :3] = np.array([2.0, 2.0, 2.0, 2.0, 2.0, 2.0, 0.5])[:, None] * 1e-3 * axis
    env._scripted = np.array([False, False, False, True, False, False, False])
    e = env._controller_reference()[0].numpy() - env.pos
    np.testing.assert_allclose(np.einsum("nk,nk->n", e, axis), [0.01, 0.01, 0.0, 0.002, -0.005, 0.015, 0.002],
                               atol=1e-12)
    for bad in ({"ik_lead_sliding": 0.01}, {"ik_bound_tool_axis": 0.02, "ik_lead_sliding": 0.03},
                {"ik_bound_tool_axis": 0.02, "ik_lead_sliding": -0.001}):
        with pytest.raises(ConfigError, match="ik_lead_sliding"):
            _cfg({"panda": bad})
    with pytest.raises(ConfigError, match="sliding_speed"):
        _cfg({"panda": {"sliding_speed": -1.0}})


def test_an_engaged_tool_between_the_walls_keeps_its_reference_not_behind_it() -> None:
    """With `ik_lead_engaged`, a tool the block pressed back along its axis (by more than `blocked_force`) while its
    scene reference advances stays engaged when it reads no contact (a peg between the bore's walls): a scene
    reference 5 mm behind it is held at the tool (arm 0), not for an arm never pressed (arm 1) nor once the reference
    stops advancing (arm 0 again); a touch across the axis does not engage, and without the option the reference
    stays behind."""
    cfg = {"panda": {"ik_bound_tool_axis": 0.02, "ik_bound_blocked": 0.0, "ik_lead_sliding": 0.01,
                     "ik_lead_engaged": True}}
    env = PandaEnv(2, _cfg(cfg), seed=0)
    off = PandaEnv(1, _cfg({"panda": {**cfg["panda"], "ik_lead_engaged": False}}), seed=0)

    def reference_along(e: PandaEnv, pressed: float, across: float = 0.0) -> np.ndarray:
        """The controller's reference along the tool axis [m] with the scene's 5 mm behind, advancing 4 mm a step,
        the tool pushed back along its axis by `pressed` and sideways by `across` [N]."""
        axis = e.rot[:, :, 2]
        e.scene.pos_d[:] = e.pos - 0.005 * axis
        e._ref_step[:] = 0.004 * axis
        e._twist[:] = 0.0
        e.f_env = np.zeros((e.num_envs, 6))
        e.f_env[:, :3] = -pressed * axis + across * e.rot[:, :, 0]
        return np.einsum("nk,nk->n", e._controller_reference()[0].numpy() - e.pos, axis)

    env.reset()
    env._engaged[:] = [True, False]  # arm 0 was pressed earlier in this advance, where it is now
    env._press_pos[:] = env.pos
    np.testing.assert_allclose(reference_along(env, 0.0), [0.0, -0.005], atol=1e-12)
    np.testing.assert_array_equal(env._engaged, [True, False])
    env._ref_step[:] = 0.0  # the procedure's reference stops: the latch clears, the reference stays behind
    axis = env.rot[:, :, 2]
    np.testing.assert_allclose(np.einsum("nk,nk->n", env._controller_reference()[0].numpy() - env.pos, axis),
                               [-0.005, -0.005], atol=1e-12)
    np.testing.assert_array_equal(env._engaged, [False, False])
    # a press along the axis while advancing engages; the free step after it is held at the tool only with the option
    for e, expect in ((env, 0.0), (off, -0.005)):
        e.reset()
        reference_along(e, 8.0)
        np.testing.assert_allclose(reference_along(e, 0.0), expect, atol=1e-12)
    # a wall touched across the axis (a peg sliding straight into the bore) keeps the tool-in-contact rule only
    env.reset()
    np.testing.assert_allclose(reference_along(env, 0.0, across=8.0), [0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(reference_along(env, 0.0), [-0.005, -0.005], atol=1e-12)
    with pytest.raises(ConfigError, match="ik_lead_engaged.*needs ik_bound_tool_axis"):
        _cfg({"panda": {"ik_lead_engaged": True}})
    with pytest.raises(ConfigError, match="engaged_depth.*>= 0"):
        _cfg({"panda": {"engaged_depth": -0.001}})


def test_an_engaged_tool_keeps_the_rules_only_past_where_the_press_began() -> None:
    """With `engaged_depth`, an engaged tool that reads free keeps a tool-in-contact's reference (not behind it) only
    once it is that far along its axis past where the engaging press began: a peg hopping on the rim after its press
    gets the scene's reference, one 3 mm down the bore is held at the tool."""
    env = PandaEnv(1, _cfg({"panda": {"ik_bound_tool_axis": 0.02, "ik_bound_blocked": 0.0, "ik_lead_sliding": 0.01,
                                      "ik_lead_engaged": True, "engaged_depth": 0.002}}), seed=0)
    env.reset()
    axis = env.rot[:, :, 2]
    start = env.pos.copy()

    def reference_along(offset: float, pressed: float) -> float:
        """The reference along the tool axis [m] relative to a tool `offset` [m] along its axis from the start, the
        scene's 5 mm behind it and advancing, the tool pushed back along its axis by `pressed` [N]."""
        env.pos = start + offset * axis
        env.scene.pos_d[:] = env.pos - 0.005 * axis
        env._ref_step[:] = 0.004 * axis
        env._twist[:] = 0.0
        env.f_env = np.zeros((1, 6))
        env.f_env[:, :3] = -pressed * axis
        return float(np.einsum("nk,nk->n", env._controller_reference()[0].numpy() - env.pos, axis)[0])

    assert reference_along(0.0, 8.0) == pytest.approx(0.0, abs=1e-12)  # pressed on the rim: the contact rule
    assert env._engaged[0]
    assert reference_along(0.0005, 0.0) == pytest.approx(-0.005, abs=1e-12)  # hopping on the rim: the scene's
    assert reference_along(-0.0005, 0.0) == pytest.approx(-0.005, abs=1e-12)
    assert reference_along(0.003, 0.0) == pytest.approx(0.0, abs=1e-12)  # between the walls: not behind it
    assert env._engaged[0]


def test_with_the_mean_filter_the_reference_rules_read_the_observed_wrench() -> None:
    """With `observation_filter: mean` the contact and the press that the tool-axis rules test are the period's mean
    wrench, which the agents observe: a last 1-kHz sample in contact over a free mean sets no lead (arm 0), a free
    last sample under a pressed mean leaves the tool blocked (arm 1)."""
    cfg = {"panda": {"ik_bound_tool_axis": 0.02, "ik_bound_blocked": 0.0, "ik_lead_sliding": 0.01,
                     "observation_filter": "mean"}}
    env = PandaEnv(2, _cfg(cfg), seed=0)
    env.reset()
    axis = env.rot[:, :, 2]
    env.scene.pos_d[:] = env.pos + 0.002 * axis
    env._ref_step[:] = 0.004 * axis
    env._twist[:] = 0.0
    env._twist[0, :3] = 0.002 * axis[0]
    env.f_env, env.f_env_obs = np.zeros((2, 6)), np.zeros((2, 6))
    env.f_env[0, :3] = -3.0 * axis[0]
    env.f_env_obs[1, :3] = -8.0 * axis[1]
    env._scripted = np.array([False, False])
    e = env._controller_reference()[0].numpy() - env.pos
    np.testing.assert_allclose(np.einsum("nk,nk->n", e, axis), [0.002, 0.0], atol=1e-12)


def test_the_blocked_bound_needs_the_tool_axis_bound_and_lies_within_it() -> None:
    with pytest.raises(ConfigError, match="ik_bound_blocked.*needs ik_bound_tool_axis"):
        _cfg({"panda": {"ik_bound_blocked": 0.0}})
    with pytest.raises(ConfigError, match="ik_bound_blocked"):
        _cfg({"panda": {"ik_bound_tool_axis": 0.02, "ik_bound_blocked": 0.03}})
    with pytest.raises(ConfigError, match="blocked_speed"):
        _cfg({"panda": {"blocked_speed": 0.0}})


def test_the_config_may_be_a_yaml_path_and_nothing_else_but_a_config() -> None:
    from pathlib import Path

    path = Path(__file__).resolve().parents[1] / "configs" / "panda_polishing.yaml"
    env = PandaEnv(1, str(path))
    assert env.pcfg.scene == "polishing"
    with pytest.raises(TypeError, match="config must be an ExperimentConfig .* or a YAML path, got dict"):
        PandaEnv(1, {"panda": {}})


def test_an_action_with_a_graph_is_detached_and_a_bad_one_named() -> None:
    """A policy run without no_grad: the env's state and outputs carry no graph. A missing action, or NaN in one arm's,
    is a ValueError that names it (no arm steps)."""
    env = PandaEnv(2, _cfg(), seed=0)
    td = env.reset()
    net = torch.nn.Linear(3, 4)
    td["action"] = torch.tanh(net(td["observation"]))
    out = env.step(td)["next"]
    assert not out["observation"].requires_grad and not out["reward"].requires_grad
    q = env.q.copy()
    with pytest.raises(ValueError, match="no 'action' entry"):
        env.step(out.clone())
    bad = torch.zeros(2, 6, 4)
    bad[1, 3, 0] = float("nan")
    with pytest.raises(ValueError, match=r"NaN or inf in batch row\(s\) \[1\]"):
        env.step(out.clone().set("action", bad))
    assert np.array_equal(env.q, q)


def test_actions_outside_the_spec_saturate_at_its_bounds() -> None:
    """Eq. 29 clips the rates to [-1, 1]: a policy whose actions overshoot the spec moves the arm as one at the bound."""
    ends = []
    for scale in (1.0, 5.0):
        env = PandaEnv(2, _cfg(), seed=0)
        td = env.reset()
        g = torch.Generator().manual_seed(1)
        for _ in range(15):
            td["action"] = (torch.rand(2, 6, 4, generator=g) * 2 - 1).sign() * scale
            td = env.step(td)["next"]
        ends.append((env.q.copy(), env.weights.copy(), env.f_d.copy(), td["reward"].clone()))
    for at_bound, beyond in zip(*ends):
        assert (np.asarray(at_bound) == np.asarray(beyond)).all()
    assert np.abs(ends[0][0] - PandaEnv(2, _cfg(), seed=0).q).max() > 0  # the actions moved the arm
