"""A2C: hand-derived gradients vs autograd, n-step returns, training, checkpoints, resume, policy loading."""

import csv
import gc
import math

import pytest
import torch

from a3cqp_rl.config import config_from_dict
from a3cqp_rl.exceptions import CheckpointError
from a3cqp_rl.regions import check_fig5_regions
from algorithms.a2c import Batch, HeldNoise, a2c_update, gae_advantages, load_policy, nstep_returns, train
from algorithms.networks import LOG_2PI, ActorCritic, ParamLayout, backward, forward, policy_forward


def random_batch(T=4, N=3, seed=0, dtype=torch.float64, obs_dim=3):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=dtype)
    term = r(T, N) < 0.2
    trunc = (r(T, N) < 0.2) & ~term
    return Batch(r(T, N, obs_dim), 2 * r(T, N, 4) - 1, r(T, N) - 0.5, term, trunc, r(T, N, obs_dim))


def test_nstep_returns_by_hand():
    g = 0.9
    rew = torch.tensor([[1.0], [2.0], [3.0]])
    nv = torch.tensor([[10.0], [20.0], [30.0]])
    f = torch.zeros(3, 1, dtype=torch.bool)
    # no episode end: bootstrap from V(s'_2) only
    R = nstep_returns(rew, f, f, nv, g)
    assert torch.allclose(R[:, 0], torch.tensor([1 + g * 2 + g * g * 3 + g**3 * 30, 2 + g * 3 + g * g * 30, 3 + g * 30]))
    # terminated at t=1: no bootstrap there, t=0 sees only r0 + g r1
    term = torch.tensor([[False], [True], [False]])
    R = nstep_returns(rew, term, f, nv, g)
    assert torch.allclose(R[:, 0], torch.tensor([1 + g * 2, 2.0, 3 + g * 30]))
    # truncated at t=1: bootstrap from V(s'_1) = 20 (the final observation), not from later steps
    R = nstep_returns(rew, f, term, nv, g)
    assert torch.allclose(R[:, 0], torch.tensor([1 + g * (2 + g * 20), 2 + g * 20, 3 + g * 30]))


def test_gae_limits_and_hand_case():
    b = random_batch(T=5, N=4, seed=3)
    g = torch.Generator().manual_seed(4)
    v, nv = torch.randn(5, 4, generator=g, dtype=torch.float64), torch.randn(5, 4, generator=g, dtype=torch.float64)
    # consistent data: V(s_{t+1}) = V(s'_t) unless the episode ended at t
    v[1:] = torch.where(b.terminated[:-1] | b.truncated[:-1], v[1:], nv[:-1])
    # λ = 1 is the n-step advantage; λ = 0 the one-step TD error
    assert torch.allclose(gae_advantages(b.rewards, b.terminated, b.truncated, v, nv, 0.9, 1.0),
                          nstep_returns(b.rewards, b.terminated, b.truncated, nv, 0.9) - v, atol=1e-12)
    td = b.rewards + 0.9 * nv * (~b.terminated) - v
    assert torch.allclose(gae_advantages(b.rewards, b.terminated, b.truncated, v, nv, 0.9, 0.0), td, atol=1e-12)
    # two steps, no episode end, λ = 0.5: A0 = δ0 + γλ δ1
    r, f = torch.tensor([[1.0], [2.0]]), torch.zeros(2, 1, dtype=torch.bool)
    A = gae_advantages(r, f, f, torch.tensor([[0.5], [1.0]]), torch.tensor([[1.0], [3.0]]), 0.9, 0.5)
    d0, d1 = 1 + 0.9 * 1.0 - 0.5, 2 + 0.9 * 3.0 - 1.0
    assert torch.allclose(A[:, 0], torch.tensor([d0 + 0.45 * d1, d1]))


@pytest.mark.parametrize("network,critic_dim,lam,bound", [("separate", None, 1.0, 0.0), ("shared", None, 1.0, 0.0),
                                                          ("separate", 7, 1.0, 0.0), ("separate", 7, 0.6, 0.7)])
@pytest.mark.parametrize("normalize", [False, True])
def test_hand_gradients_equal_autograd(network, critic_dim, lam, bound, normalize):
    cfg = config_from_dict({"a2c": {"network": network, "normalize_advantage": normalize, "hidden": [8, 6],
                                    "gae_lambda": lam, "bound_coef": bound,
                                    "max_grad_norm": 1e9, "learning_rate": 1.0, "rms_alpha": 0.0, "rms_eps": 1e-300}})
    hp = cfg.a2c
    layout = ParamLayout(3, 4, hp.hidden, network, critic_dim)
    flat = layout.init(torch.Generator().manual_seed(0)).double()
    flat += (0.1 + 2 * bound) * torch.randn(flat.shape, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    batch = random_batch(obs_dim=critic_dim or 3)
    # autograd reference of the same loss (SB3's A2C loss)
    ac = ActorCritic(layout, flat)
    T, N = batch.rewards.shape
    D = batch.obs.shape[-1]
    mu, log_std, v = ac(batch.obs.reshape(T * N, D))
    with torch.no_grad():
        nv = ac(batch.next_obs.reshape(T * N, D))[2].reshape(T, N)
    if lam == 1.0:  # the paper's n-step returns
        R = nstep_returns(batch.rewards, batch.terminated, batch.truncated, nv, hp.gamma).reshape(-1)
    else:
        R = gae_advantages(batch.rewards, batch.terminated, batch.truncated, v.detach().reshape(T, N), nv,
                           hp.gamma, lam).reshape(-1) + v.detach()
    adv = (R - v).detach()
    if normalize:
        adv = (adv - adv.mean()) / (adv.std() + 1e-8)
    logp = ac.log_prob(mu, log_std, batch.actions.reshape(T * N, 4))
    ent = (log_std + 0.5 * (1 + LOG_2PI)).sum()
    loss = -(adv * logp).mean() + hp.vf_coef * ((R - v) ** 2).mean() - hp.ent_coef * ent
    loss = loss + bound * (mu.abs() - 1.0).clamp(min=0.0).pow(2).sum(-1).mean()
    loss.backward()
    ref = ac.flat.grad
    # with alpha=0, eps≈0, lr=1 the RMSProp step is -grad/|grad| per element: recover grad direction and norm
    sq = torch.zeros_like(flat)
    before = flat.clone()
    metrics = a2c_update(layout, flat, sq, batch, hp)
    assert torch.allclose(sq.sqrt(), ref.abs(), rtol=1e-9, atol=1e-12)  # accumulator = grad² exactly
    step = before - flat
    nz = ref.abs() > 1e-12
    assert torch.equal(torch.sign(step[nz]), torch.sign(ref[nz]))
    assert metrics[3] == pytest.approx(ref.norm().item(), rel=1e-9)


@pytest.mark.parametrize("network,critic_dim", [("separate", None), ("shared", None), ("separate", 7)])
def test_update_reusing_the_acting_activations_equals_recomputing_them(network, critic_dim):
    hp = config_from_dict({"a2c": {"network": network, "hidden": [8, 6], "learning_rate": 1e-2}}).a2c
    layout = ParamLayout(3, 4, hp.hidden, network, critic_dim)
    flat = layout.init(torch.Generator().manual_seed(0)).double()
    batch = random_batch(obs_dim=critic_dim or 3)
    T, N, D = batch.obs.shape
    _, acts = policy_forward(layout, flat, batch.obs.reshape(T * N, D))
    reused = Batch(*(getattr(batch, f) for f in ("obs", "actions", "rewards", "terminated", "truncated", "next_obs")),
                   tuple(a.reshape(T, N, -1) for a in acts[1:]))
    flat_a, flat_b = flat.clone(), flat.clone()
    sq_a, sq_b = torch.zeros_like(flat), torch.zeros_like(flat)
    m_a = a2c_update(layout, flat_a, sq_a, batch, hp)
    m_b = a2c_update(layout, flat_b, sq_b, reused, hp)
    assert torch.allclose(m_a, m_b, rtol=1e-12, atol=1e-12)
    assert torch.allclose(flat_a, flat_b, rtol=0, atol=1e-12) and not torch.equal(flat_a, flat)
    assert torch.allclose(sq_a, sq_b, rtol=1e-12, atol=1e-20)


def test_backward_matches_autograd_for_arbitrary_output_gradients():
    layout = ParamLayout(3, 4, (5, 7), "shared")
    flat = layout.init(torch.Generator().manual_seed(2)).double().requires_grad_()
    x = torch.randn(6, 3, dtype=torch.float64)
    mu, ls, v, cache = forward(layout, flat, x)
    gm, gl, gv = torch.randn_like(mu), torch.randn_like(ls), torch.randn_like(v)
    (mu * gm).sum().add_((ls * gl).sum()).add_((v * gv).sum()).backward()
    ours = backward(layout, flat.detach(), cache, gm, gl, gv)
    assert torch.allclose(ours, flat.grad, atol=1e-12)


def test_privileged_critic_layout_reads_more_but_policy_does_not():
    layout = ParamLayout(3, 4, (5,), "separate", critic_obs_dim=9)
    flat = layout.init(torch.Generator().manual_seed(0))
    x = torch.rand(6, 9)
    y = x.clone()
    y[:, 3:] += 1.0  # privileged columns change: the value does, the policy mean does not
    mu_x, _, v_x, _ = forward(layout, flat, x)
    mu_y, _, v_y, _ = forward(layout, flat, y)
    assert torch.equal(mu_x, mu_y) and not torch.allclose(v_x, v_y)
    with pytest.raises(ValueError, match="separate"):
        ParamLayout(3, 4, (5,), "shared", critic_obs_dim=9)
    with pytest.raises(ValueError, match=">= obs_dim"):
        ParamLayout(3, 4, (5,), "separate", critic_obs_dim=2)


@pytest.mark.parametrize("rollout", ["auto", "torchrl"])
def test_train_with_privileged_critic_and_gae(tmp_path, rollout):
    cfg = config_from_dict({"a2c": {"compile": False, "critic": "privileged", "gae_lambda": 0.5, "rollout": rollout,
                                    "log_every": 20}, "point_mass": {"episode_steps": 20}})
    res = train(cfg, tmp_path / rollout, total_steps=16 * 40)
    assert math.isfinite(res.final_metrics["value_loss"]) and res.episode_returns
    policy = load_policy(res.policy_path)  # the saved policy still maps the 3-d eq. 26 observation
    assert policy(torch.rand(5, 3)).shape == (5, 4)


def test_held_noise_redraws_every_k_steps_and_resumes():
    white = HeldNoise(torch.Generator().manual_seed(0), 3, 4, hold=1).draw(5)
    assert torch.equal(white, torch.randn(5, 3, 4, generator=torch.Generator().manual_seed(0)))  # paper/SB3 default
    h = HeldNoise(torch.Generator().manual_seed(0), 3, 4, hold=3)
    a = torch.cat([h.draw(4), h.draw(4)])  # steps 0..7: draws at 0, 3, 6 across the call boundary
    assert torch.equal(a[0], a[1]) and torch.equal(a[1], a[2]) and not torch.equal(a[2], a[3])
    assert torch.equal(a[3], a[5]) and not torch.equal(a[5], a[6]) and torch.equal(a[6], a[7])
    gen = torch.Generator().manual_seed(1)
    h1 = HeldNoise(gen, 2, 4, hold=5)
    h1.draw(7)
    snap, gstate = h1.state_dict(), gen.get_state()
    later = h1.draw(6)
    gen2 = torch.Generator()
    gen2.set_state(gstate)
    h2 = HeldNoise(gen2, 2, 4, hold=5)
    h2.load_state_dict(snap)
    assert torch.equal(h2.draw(6), later)


def test_train_short_run_writes_files_and_learns_something(tmp_path):
    cfg = config_from_dict({"a2c": {"compile": False, "log_every": 50, "checkpoint_every": 100}})
    res = train(cfg, tmp_path / "run", total_steps=16 * 200)
    assert res.steps == 3200 and res.updates == 200
    for name in ("metrics.csv", "checkpoint.pt", "policy.pt", "config.yaml"):
        assert (tmp_path / "run" / name).is_file()
    rows = (tmp_path / "run" / "metrics.csv").read_text().strip().splitlines()
    assert len(rows) == 1 + 4 and rows[0].startswith("step,update,policy_loss")
    # the Fig. 5 region columns: checked on every row here (4 rows <= region_checks), the last = the saved policy's
    with (tmp_path / "run" / "metrics.csv").open() as f:
        table = list(csv.DictReader(f))
    flags = [[float(r[f"region_{k}"]) for k in ("w2", "w3", "fd", "w1")] for r in table]
    assert all(set(f) <= {0.0, 1.0} and sum(f) == float(r["regions_ok"]) for f, r in zip(flags, table))
    final = check_fig5_regions(load_policy(tmp_path / "run" / "policy.pt"))
    assert flags[-1] == [float(r.ok) for r in final]
    policy = load_policy(tmp_path / "run" / "policy.pt")
    a = policy(torch.rand(7, 5, 3))
    assert a.shape == (7, 5, 4) and a.abs().max() <= 1.0
    with pytest.raises(ValueError, match="last dim"):
        policy(torch.rand(2, 4))
    with pytest.raises(ValueError, match="NaN"):
        policy(torch.full((2, 3), float("nan")))


@pytest.mark.parametrize("hold,backend", [(1, "torch"), (7, "torch"), (1, "native"), (7, "native")])
def test_same_seed_same_numbers_and_resume_is_exact(tmp_path, hold, backend):
    base = {"a2c": {"compile": False, "log_every": 10, "checkpoint_every": 25, "noise_hold": hold, "backend": backend},
            "point_mass": {"episode_steps": 30}}
    cfg = config_from_dict(base)
    full = train(cfg, tmp_path / "full", total_steps=16 * 50)
    again = train(cfg, tmp_path / "again", total_steps=16 * 50)
    p_full = torch.load(tmp_path / "full" / "policy.pt", weights_only=True)["flat"]
    p_again = torch.load(tmp_path / "again" / "policy.pt", weights_only=True)["flat"]
    assert torch.equal(p_full, p_again)
    # "killed" after 25 updates (checkpoint), then resumed to 50: identical parameters and metrics
    train(cfg, tmp_path / "part", total_steps=16 * 25)
    train(cfg, tmp_path / "part", total_steps=16 * 50, resume=True)
    p_part = torch.load(tmp_path / "part" / "policy.pt", weights_only=True)["flat"]
    assert torch.equal(p_full, p_part)
    def rows(run):  # steps/s differs, nothing else (region checks included)
        with (tmp_path / run / "metrics.csv").open() as f:
            return [{k: v for k, v in r.items() if k != "steps_per_second"} for r in csv.DictReader(f)]

    assert rows("full") == rows("part") and rows("full")[-1]["regions_ok"] != "nan"
    assert full.episode_returns  # 30-step episodes ended and were counted


def test_resuming_a_run_logged_before_the_region_columns_keeps_its_rows(tmp_path):
    from algorithms.a2c import CSV_COLUMNS, _truncate_csv

    path = tmp_path / "metrics.csv"
    path.write_text("step,update,policy_loss\n16,1,0.5\n32,2,0.25\n48,3,0.125\n")
    _truncate_csv(path, keep_until_update=2, log_every=1)
    with path.open() as f:
        rows = list(csv.DictReader(f))
    assert list(rows[0]) == list(CSV_COLUMNS) and [r["policy_loss"] for r in rows] == ["0.5", "0.25"]
    assert rows[0]["regions_ok"] == "nan"
    path.write_text("garbage\n")  # no rows under a header of another program: the resumed log gets its own header
    _truncate_csv(path, keep_until_update=2, log_every=1)
    assert path.read_text().splitlines() == [",".join(CSV_COLUMNS)]


def test_missing_and_corrupt_checkpoints(tmp_path):
    cfg = config_from_dict({"a2c": {"compile": False}})
    with pytest.raises(CheckpointError, match="not found"):
        train(cfg, tmp_path / "none", total_steps=16, resume=True)
    (tmp_path / "bad").mkdir()
    (tmp_path / "bad" / "checkpoint.pt").write_bytes(b"not a checkpoint")
    with pytest.raises(CheckpointError, match="corrupt"):
        train(cfg, tmp_path / "bad", total_steps=16, resume=True)
    with pytest.raises(CheckpointError, match="not found"):
        load_policy(tmp_path / "nope.pt")
    with pytest.raises(TypeError, match="needs an ExperimentConfig"):
        train("configs/point_mass_a2c.yaml", tmp_path / "str", total_steps=16)


def test_a_policy_with_non_finite_parameters_is_refused_and_a_run_folder_loads(tmp_path):
    import shutil

    from pathlib import Path

    from a3cqp_rl.checkpoint import load_checkpoint, save_atomic

    shipped = Path(__file__).resolve().parents[1] / "policies" / "point_mass_fig5_fd_1e6_seed0.pt"
    (tmp_path / "run").mkdir()
    shutil.copy(shipped, tmp_path / "run" / "policy.pt")
    assert load_policy(tmp_path / "run").layout.size == load_policy(shipped).layout.size  # the folder's policy.pt
    data = load_checkpoint(shipped, ("flat", "layout"))
    data["flat"] = data["flat"].clone()
    data["flat"][3] = float("nan")
    save_atomic(data, tmp_path / "nan.pt")
    with pytest.raises(CheckpointError, match="1 of its .* parameters are not finite"):
        load_policy(tmp_path / "nan.pt")
    newer = load_checkpoint(shipped, ("flat", "layout"))
    save_atomic({**newer, "format": 99}, tmp_path / "newer.pt")  # a file of a later version: refused, not misread
    with pytest.raises(CheckpointError, match="has format 99; this version reads format 1"):
        load_policy(tmp_path / "newer.pt")


def test_torchrl_collector_path_trains_on_a_plain_envbase():
    from torchrl.envs import SerialEnv

    from envs.point_mass import PointMassEnv

    cfg = config_from_dict({"a2c": {"compile": False, "log_every": 5, "num_envs": 2}, "point_mass": {"episode_steps": 12}})
    env = SerialEnv(2, lambda: PointMassEnv(1, cfg, seed=0))  # no fused API: the trainer uses a TorchRL Collector
    res = train(cfg, None, total_steps=2 * 4 * 10, env=env)
    assert res.updates == 10 and math.isfinite(res.final_metrics["value_loss"])
    assert len(res.episode_returns) >= 2  # truncations seen through the collector


def test_rollout_torchrl_option_uses_collector_on_batched_env():
    cfg = config_from_dict({"a2c": {"compile": False, "log_every": 5, "rollout": "torchrl"}, "point_mass": {"episode_steps": 8}})
    res = train(cfg, None, total_steps=16 * 5)
    assert res.updates == 5 and len(res.episode_returns) == 8  # 4 envs x 2 episodes of 8 steps in 20 steps


def test_split_and_fused_rollouts_give_the_same_numbers():
    from algorithms.a2c import FusedRollout
    from envs.point_mass import PointMassEnv

    cfg = config_from_dict({"a2c": {"compile": False, "n_steps": 5, "backend": "torch"},
                            "point_mass": {"episode_steps": 12}})
    flats = []
    for fuse in (True, False):
        env = PointMassEnv(3, cfg, seed=4)
        env.reset()
        layout = ParamLayout(3, 4, cfg.a2c.hidden, cfg.a2c.network)
        gen = torch.Generator().manual_seed(0)
        flat = layout.init(gen)
        sq = torch.zeros_like(flat)
        runner = FusedRollout(env, layout, gen, cfg.a2c, fuse=fuse)
        metrics = [runner.iterate(flat, sq) for _ in range(6)]  # crosses two episode ends
        flats.append((flat, torch.stack(metrics), runner.finished))
    assert torch.equal(flats[0][0], flats[1][0]) and torch.equal(flats[0][1], flats[1][1])
    assert flats[0][2] == flats[1][2] and len(flats[0][2]) == 6


def test_compiled_functions_do_not_share_graphs() -> None:
    """Two functions from the same `def` (two trainers' closures) keep their own compiled graphs.

    Regression: dynamo caches graphs on the code object and `_compile` skips the guards, so a second
    trainer with another config used to run the first one's graph (its hyper-parameters baked in).
    """
    from algorithms.a2c import _compile

    def make(k: float):
        def scale(x: torch.Tensor) -> torch.Tensor:
            return x * k
        return scale

    first, second = _compile(make(2.0)), _compile(make(3.0))
    x = torch.ones(3)
    assert torch.equal(first(x), 2.0 * x)
    assert torch.equal(second(x), 3.0 * x)


def test_average_last_saves_the_mean_of_the_final_parameters_and_resumes_exactly(tmp_path):
    base = {"a2c": {"compile": False, "log_every": 1, "checkpoint_every": 3, "region_checks": 0, "learning_rate": 1e-2},
            "point_mass": {"episode_steps": 30}}
    raw = []  # the parameters after each update k = 1..8 (a k-update run is the prefix of a longer one)
    for k in range(1, 9):
        train(config_from_dict(base), tmp_path / f"raw{k}", total_steps=16 * k)
        raw.append(torch.load(tmp_path / f"raw{k}" / "policy.pt", weights_only=True)["flat"])
    avg_cfg = config_from_dict({**base, "a2c": {**base["a2c"], "average_last": 0.5}})
    train(avg_cfg, tmp_path / "avg", total_steps=16 * 8)
    saved = torch.load(tmp_path / "avg" / "policy.pt", weights_only=True)
    assert saved["averaged_updates"] == 4
    assert torch.allclose(saved["flat"], torch.stack(raw[4:]).mean(0), atol=1e-6)  # updates 5-8
    assert not torch.allclose(saved["flat"], raw[-1], atol=1e-4)
    ck = torch.load(tmp_path / "avg" / "checkpoint.pt", weights_only=True)
    assert torch.equal(ck["flat"], raw[-1])  # training itself runs on the raw parameters

    # killed after update 7 (last checkpoint: 6, inside the window), resumed: the same average
    def kill(step, row):
        if step == 16 * 7:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(avg_cfg, tmp_path / "killed", total_steps=16 * 8, callback=kill)
    train(avg_cfg, tmp_path / "killed", total_steps=16 * 8, resume=True)
    assert torch.equal(torch.load(tmp_path / "killed" / "policy.pt", weights_only=True)["flat"], saved["flat"])
    # extended to 12 updates: the new window (7-12) began before the checkpoint (8), so it says what it averages
    with pytest.warns(UserWarning, match="averages 9-12"):
        train(avg_cfg, tmp_path / "killed", total_steps=16 * 12, resume=True)
    assert torch.load(tmp_path / "killed" / "policy.pt", weights_only=True)["averaged_updates"] == 4
    with pytest.raises(ValueError, match="average_last"):
        config_from_dict({"a2c": {"average_last": 1.0}})


def test_tensorboard_scalars_match_metrics_csv_and_a_resume_hides_the_killed_runs_extra_rows(tmp_path):
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    cfg = config_from_dict({"a2c": {"compile": False, "log_every": 1, "checkpoint_every": 3, "region_checks": 2},
                            "point_mass": {"episode_steps": 30}})

    def kill(step, row):
        if step == 16 * 5:  # rows 4 and 5 are past the last checkpoint (3)
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(cfg, tmp_path / "run", total_steps=16 * 8, callback=kill)
    gc.collect()  # the killed run's writer flushes when collected
    killed = EventAccumulator(str(tmp_path / "run" / "tb"))
    killed.Reload()
    assert [e.step for e in killed.Scalars("a2c/policy_loss")] == [16, 32, 48, 64, 80]
    train(cfg, tmp_path / "run", total_steps=16 * 8, resume=True)
    events = EventAccumulator(str(tmp_path / "run" / "tb"))
    events.Reload()
    with (tmp_path / "run" / "metrics.csv").open() as f:
        rows = list(csv.DictReader(f))
    loss = events.Scalars("a2c/policy_loss")
    assert [e.step for e in loss] == [int(r["step"]) for r in rows] == [16 * k for k in range(1, 9)]
    assert [e.value for e in loss] == pytest.approx([float(r["policy_loss"]) for r in rows], rel=1e-6)
    checks = [int(r["step"]) for r in rows if r["regions_ok"] != "nan"]
    assert [e.step for e in events.Scalars("a2c/regions_ok")] == checks  # NaN cells are not logged


def test_init_policy_starts_from_a_saved_actor_and_keeps_a_critic_that_does_not_fit(tmp_path):
    from a3cqp_rl.checkpoint import save_atomic
    from algorithms.policy import init_from_policy

    # a point-mass-style file with a privileged critic (input 3 + 3) onto a run whose critic reads eq. 26 only
    src = ParamLayout(3, 4, (8, 6), "separate", 6)
    flat_src = src.init(torch.Generator().manual_seed(1), -0.3)
    save_atomic({"format": 1, "flat": flat_src, "layout": [3, 4, [8, 6], "separate", 6],
                 "action_low": [-1.0] * 4, "action_high": [1.0] * 4}, tmp_path / "pm" / "policy.pt")
    dst = ParamLayout(3, 4, (8, 6), "separate")
    flat = dst.init(torch.Generator().manual_seed(2), -0.5)
    before = dst.views(flat.clone())
    copied = init_from_policy(tmp_path / "pm", dst, flat, (-1.0,) * 4, (1.0,) * 4)
    got, want = dst.views(flat), src.views(flat_src)
    assert "vf.0.w" not in copied and torch.equal(got["vf.0.w"], before["vf.0.w"])
    for k in ("pi.0.w", "pi.1.b", "pi.out.w", "log_std", "vf.1.w", "vf.out.b"):
        assert k in copied and torch.equal(got[k], want[k])
    with pytest.raises(CheckpointError, match="action bounds"):
        init_from_policy(tmp_path / "pm", dst, flat, (-2.0,) * 4, (2.0,) * 4)
    with pytest.raises(CheckpointError, match="does not fit"):
        wide = ParamLayout(3, 4, (16, 6), "separate")
        init_from_policy(tmp_path / "pm", wide, wide.init())
    # through train(): a run with a vanishing learning rate saves the actor it started from
    cfg = config_from_dict({"a2c": {"compile": False, "hidden": [8, 6], "learning_rate": 1e-30, "critic": "privileged",
                                    "init_policy": str(tmp_path / "pm" / "policy.pt"), "log_every": 5}})
    train(cfg, tmp_path / "run", total_steps=16 * 10)
    saved = torch.load(tmp_path / "run" / "policy.pt", weights_only=True)
    run = ParamLayout(*saved["layout"]).views(saved["flat"])
    for k in ("pi.0.w", "pi.0.b", "pi.1.w", "pi.out.w", "pi.out.b", "log_std"):
        assert torch.allclose(run[k], want[k], atol=1e-6)
