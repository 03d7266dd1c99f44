"""Slow: full trainings checked against the paper's Fig. 5 regions (run with `pytest -m slow`)."""

from pathlib import Path

import pytest

from a3cqp_rl.config import load_config
from a3cqp_rl.regions import check_fig5_regions
from algorithms.a2c import load_policy, train

CONFIGS = Path(__file__).parents[1] / "configs"


@pytest.fixture(scope="module")
def fig5_regions(tmp_path_factory):
    """Train configs/point_mass_a2c_fig5.yaml for its 2e7 steps (~4 min on 2 cores) once; region results by name."""
    cfg = load_config(CONFIGS / "point_mass_a2c_fig5.yaml")
    res = train(cfg, tmp_path_factory.mktemp("fig5"))
    return {r.name: r for r in check_fig5_regions(load_policy(res.policy_path))}


@pytest.mark.slow
@pytest.mark.parametrize("region", ["w1_ik_when_free_with_error", "w2_admittance_when_operator_pushes",
                                    "w3_force_control_in_contact"])
def test_fig5_config_learns_task_weight_regions(fig5_regions, region):
    r = fig5_regions[region]
    assert r.ok, r


@pytest.mark.slow
@pytest.mark.xfail(reason="eq. 30 pays pressing only 1/60 per N per step; f_d stays low in contact "
                          "(see configs/point_mass_a2c_fig5.yaml)", strict=False)
def test_fig5_config_learns_desired_force_region(fig5_regions):
    r = fig5_regions["fd_desired_force_in_contact"]
    assert r.ok, r


@pytest.mark.slow
def test_fig5_fd_config_learns_at_least_three_of_the_four_regions(tmp_path):
    """configs/point_mass_a2c_fig5_fd.yaml (α3 = 4, walls 5-15 cm; 4e7 steps, ~2 min on 2 cores): at least three of
    the four checks, ẇ3 among them. (All four on seed 0 with two torch threads, on seed 2 with one; the config's
    comment has the per-seed results: which check fails depends on the float summation order.)"""
    cfg = load_config(CONFIGS / "point_mass_a2c_fig5_fd.yaml")
    res = train(cfg, tmp_path)
    results = check_fig5_regions(load_policy(res.policy_path))
    assert sum(r.ok for r in results) >= 3 and results[1].ok, results


@pytest.mark.slow
@pytest.mark.xfail(reason="not reproduced: within the paper's 1e6 steps no setting found passes all 4 Fig. 5 checks "
                          "(see configs/point_mass_a2c_tuned.yaml and the README)", strict=False)
def test_tuned_config_learns_fig5_regions_in_1e6_steps(tmp_path):
    cfg = load_config(CONFIGS / "point_mass_a2c_tuned.yaml")
    res = train(cfg, tmp_path, total_steps=1_000_000)
    results = check_fig5_regions(load_policy(res.policy_path))
    assert all(r.ok for r in results), results


@pytest.mark.slow
@pytest.mark.parametrize("seed", [0, 1])
def test_fd_1e6_config_learns_three_of_four_regions_in_1e6_steps(tmp_path, seed):
    """configs/point_mass_a2c_fig5_fd_1e6.yaml: the paper's 1e6 steps (~5 s each on the C iteration), 3 of 4 checks on
    the run's last parameters. (The config's `select_policy: panda` keeps, in policy.pt, the parameters that insert
    most pegs on the Panda, chosen for the robot and not for the regions: seed 1's fails ẇ3. The selection has its
    own tests, tests/test_panda_select.py.)"""
    cfg = load_config(CONFIGS / "point_mass_a2c_fig5_fd_1e6.yaml", {"seed": seed, "a2c": {"select_policy": "last"}})
    res = train(cfg, tmp_path)
    assert res.steps == 1_000_000
    results = check_fig5_regions(load_policy(res.policy_path))
    assert sum(r.ok for r in results) >= 3, results
    assert results[1].ok, results  # ẇ3, force control in contact: passed on all five seeds measured


@pytest.mark.slow
def test_default_config_behaves_in_closed_loop(tmp_path):
    """configs/point_mass_a2c_default.yaml (`make train`; ~2-5 min on 2 cores), seed 100: all four literal regions
    and every closed-loop check against the five baselines (docs/point_mass.md)."""
    from envs.point_mass_eval import baseline_policies, behaviour_checks, evaluate

    cfg = load_config(CONFIGS / "point_mass_a2c_default.yaml", {"seed": 100})
    res = train(cfg, tmp_path)
    policy = load_policy(res.policy_path)
    literal = sum(r.literal for r in check_fig5_regions(policy))
    baselines = baseline_policies()
    result = evaluate({"policy": policy, **baselines}, episodes=64, seed=0, config=cfg)
    checks = behaviour_checks(result, "policy", literal, against=list(baselines))
    assert all(checks.values()), (checks, result.metrics["policy"])
