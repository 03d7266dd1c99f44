"""NSGA-II on the Panda: genome -> fixed controller, seeded robust trials, the population batch against one
simulation per genome, the fixed controller in `a3cqp evaluate` against its built-in twin, and --pick -> evaluate."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from a3cqp_rl.config import FixedControllerConfig, config_from_dict, load_config
from a3cqp_rl.exceptions import ConfigError
from algorithms.tuning.panda_objectives import evaluate_fixed, fixed_from_genome, trial_draws
from envs.panda_eval import evaluate, load_fixed_controller, main

ROOT = Path(__file__).resolve().parents[1]
SHORT = {"panda": {"max_episode_time": 0.3}}
"""Episodes cut after 0.3 s (300 control periods): enough to separate controllers, cheap on the Python QP path."""


def _cfg(**panda) -> object:
    return load_config(ROOT / "configs" / "nsga2_peg.yaml",
                       {**SHORT, "nsga2": {"panda": {"trials": 1, **panda}}})


def test_genome_decodes_weights_levels_and_gains() -> None:
    f = fixed_from_genome({"ik.w": [0.1, 0.2, 0.3], "fc.w": 0.5, "ac.w": [0.6, 0.7], "ik.level": 2, "jc.level": 0,
                           "ik.kp": 300.0, "ac.c_d": 7.0, "jc.w": 2.0, "fc.f_d": 12.0, "cartesian_regularizer.w": 1e-3})
    assert f.weights["ik"] == (0.1, 0.1, 0.2, 0.3, 0.3, 0.3)  # size 3: x-y across the tool, z along it, rotations
    assert f.weights["fc"] == (0.5,) * 6 and f.weights["ac"] == (0.6, 0.6, 0.6, 0.7, 0.7, 0.7)
    assert f.level_row() == (2, 1, 1, 0, 1)  # ik, ac, fc, jc, cartesian_regularizer
    assert (f.kp, f.c_d, f.jc_weight, f.f_d, f.cartesian_regularization) == (300.0, 7.0, 2.0, 12.0, 1e-3)
    assert f.k_theta == 20.0 and f.lambda_d == 5.0  # not in the genome: Table I
    with pytest.raises(ConfigError, match="not a gene"):
        fixed_from_genome({"ik.bogus": 1.0})
    with pytest.raises(ConfigError, match="size 1, 2, 3 or 6"):
        fixed_from_genome({"ik.w": [0.1] * 4})


@pytest.mark.parametrize("bad, msg", [({"levels": {"ik": 4}}, "levels.ik"), ({"levels": {"foo": 1}}, "unknown task"),
                                      ({"weights": {"ik": [1.0] * 5}}, "weights.ik"), ({"name": "ik"}, "name"),
                                      ({"kp": -1.0}, "kp"), ({"f_d": 1e3}, "f_d_max")])
def test_fixed_controller_config_rejects_bad_values(bad: dict, msg: str) -> None:
    with pytest.raises(ConfigError, match=msg):
        config_from_dict({"fixed_controller": bad})


def test_trials_are_seeded_and_operator_strength_in_range() -> None:
    cfg = load_config(ROOT / "configs" / "nsga2_peg.yaml", {"nsga2": {"panda": {"trials": 5}}})
    seeds, scales = trial_draws(cfg)
    assert trial_draws(cfg)[0] == seeds and len(set(seeds)) == 5
    assert np.all((scales >= 0.7) & (scales <= 1.3)) and scales.std() > 0


@pytest.mark.slow
def test_population_batch_equals_one_simulation_per_genome() -> None:
    fixed = [FixedControllerConfig(name="table_i"),
             fixed_from_genome({"ik.w": [1.0, 0.2, 1.0], "fc.w": [0.0, 1.0, 0.0], "fc.f_d": 10.0, "ik.kp": 40.0,
                                "jc.level": 2}, "soft_z")]
    together = evaluate_fixed(fixed, _cfg(batch="population"))
    alone = evaluate_fixed(fixed, _cfg(batch="per_genome"))
    assert together.objectives.shape == (2, 3) and np.all(np.isfinite(together.objectives))
    np.testing.assert_allclose(together.objectives, alone.objectives, rtol=1e-6, atol=1e-9)
    # a soft IK (k_p 40, z weight 0.2) tracks worse than Table I's
    assert together.objectives[1, 0] > together.objectives[0, 0]


def test_fixed_controller_in_evaluate_matches_its_builtin_twin() -> None:
    """A fixed controller with IK only, f_d 0, Table I gains and one level is `ik`: same trial, same motion."""
    cfg = config_from_dict({"panda": {"max_episode_time": 0.6, "peg_in_hole": {"settle_time": 0.1}}})
    twin = FixedControllerConfig(name="ik_twin")
    res = evaluate("peg_in_hole", None, trials=1, seed=0, config=cfg, controllers=("ik",), progress=False,
                   fixed=[twin])
    assert list(res.summary) == ["ik", "ik_twin"]
    q_ik, q_twin = res.episodes["ik"]["q"], res.episodes["ik_twin"]["q"]
    assert q_ik.shape == q_twin.shape and np.abs(q_ik - q_ik[0]).max() > 1e-2  # the arm moved (the approach)
    np.testing.assert_allclose(q_twin, q_ik, atol=1e-6)


@pytest.mark.slow
def test_pareto_run_pick_is_evaluated(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    from algorithms.tuning.nsga2 import pick, read_front, tune_pareto

    cfg = load_config(ROOT / "configs" / "nsga2_peg.yaml",
                      {**SHORT, "nsga2": {"population": 2, "generations": 1, "chunk_size": 4, "panda": {"trials": 1}}})
    tune_pareto(cfg, tmp_path, progress=False, plots=True)
    front = read_front(tmp_path)
    assert len(front) >= 1 and {"tracking_cm", "interaction_n", "failure", "ik.level"} <= set(front[0])
    assert (tmp_path / "pareto.png").is_file() and (tmp_path / "pareto_3d.png").is_file()
    path = pick(tmp_path, 0)
    fixed = load_fixed_controller(path)
    assert fixed.name == "pareto_0"
    assert main(["--scene", "peg_in_hole", "--trials", "1", "--controllers", "ik", "--quiet",
                 "--config", str(tmp_path / "config.yaml"), "--controller-config", str(path)]) == 0
    assert "pareto_0" in capsys.readouterr().out


def test_evaluate_cli_reports_a_bad_controller_config_in_one_line(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    assert main(["--scene", "peg_in_hole", "--controllers", "ik", "--controller-config",
                 str(tmp_path / "missing.yaml")]) == 2
    assert "controller config not found" in capsys.readouterr().err
    plain = tmp_path / "plain.yaml"
    plain.write_text("seed: 1\n")
    assert main(["--scene", "peg_in_hole", "--controllers", "ik", "--controller-config", str(plain)]) == 2
    assert "no fixed_controller section" in capsys.readouterr().err


@pytest.mark.parametrize("scene", ["guidance", "polishing"])
def test_objective_runs_on_the_other_scenes(scene: str) -> None:
    fixed = [FixedControllerConfig(name="table_i")]
    res = evaluate_fixed(fixed, _cfg(scenes=[scene]))
    assert res.objectives.shape == (1, 3) and np.all(np.isfinite(res.objectives)) and np.all(res.objectives >= 0)
    assert set(res.per_trial) == {scene} and res.per_trial[scene]["episode_s"][0, 0] == pytest.approx(0.3, abs=0.02)


def test_evaluate_cli_names_the_files_whose_controllers_share_a_name(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """Two runs' `--pick 1` files both name their controller pareto_1: the error says which files and what to set."""
    for run in ("small", "large"):
        (tmp_path / run).mkdir()
        (tmp_path / run / "pick_1.yaml").write_text("fixed_controller:\n  name: pareto_1\n")
    files = [str(tmp_path / "small" / "pick_1.yaml"), str(tmp_path / "large" / "pick_1.yaml")]
    assert main(["--scene", "peg_in_hole", "--controllers", "ik", "--quiet", "--controller-config", *files]) == 2
    err = capsys.readouterr().err
    assert "large/pick_1.yaml names its controller 'pareto_1', as does" in err and "small/pick_1.yaml" in err
    assert "fixed_controller.name" in err


def test_a_fixed_controller_pressing_above_the_scenes_force_bound_is_refused() -> None:
    cfg = config_from_dict({"adaptation": {"f_d_max": 10.0}})
    strong = FixedControllerConfig(name="pick", f_d=15.0)  # within its own file's default bound (20 N)
    with pytest.raises(ValueError, match=r"adaptation.f_d_max \(10 N\), .*: pick \(15 N\)"):
        evaluate("peg_in_hole", None, trials=1, seed=0, config=cfg, controllers=("ik",), progress=False,
                 fixed=[strong])


def test_a_genome_with_the_regularizer_in_a_level_of_its_own_runs_its_qp() -> None:
    """A genome of `a3cqp pareto --config configs/nsga2_peg.yaml` (generation 1): (ik + ac + fc) / (regularizer) /
    (jc), IK weights plus FC's idle share above 1. Its regularizer level was NON_CONVEX: the brake at every period
    (fallback fraction 1), with a per-step log line."""
    genome = {"ik.w": [0.667, 0.669, 0.605], "ik.level": 1, "ik.kp": 70.9, "ik.k_theta": 10.68,
              "ac.w": [0.438, 0.423, 0.963], "ac.level": 1, "ac.lambda_d": 1.31, "ac.c_d": 1.23,
              "fc.w": [0.653, 0.295, 0.466], "fc.level": 1, "fc.f_d": 3.18, "jc.w": 16.5, "jc.level": 3, "jc.kq": 1.89,
              "cartesian_regularizer.w": 5.8e-4, "cartesian_regularizer.level": 2}
    res = evaluate_fixed([fixed_from_genome(genome, "g")], _cfg(scenes=["guidance"]))
    assert res.per_trial["guidance"]["fallback_fraction"][0, 0] == 0.0 and res.objectives[0, 2] == 0.0
