"""NSGA-II on pygad: the reference check against pymoo on ZDT1/ZDT2 (hypervolume at the same budget), the fast
non-dominated sort against pygad's, hypervolume against pymoo, eq. 4 level selectors, resume, --pick, plots."""

from __future__ import annotations

import csv
import re
from pathlib import Path

import numpy as np
import pygad
import pytest
import yaml

from a3cqp_rl.config import ExperimentConfig, GeneConfig, load_config
from a3cqp_rl.exceptions import ConfigError
from algorithms.tuning.genome import GenomeSpec, level_from_selector
from algorithms.tuning.nsga2 import make_problem, pareto_front, pick, rank_and_crowding, read_front, tune_pareto
from algorithms.tuning.objectives import get_objective, register
from algorithms.tuning.pareto import hypervolume, non_dominated
from algorithms.tuning.pygad_ga import GA
from algorithms.tuning.runner import build_ga, read_state

ROOT = Path(__file__).resolve().parents[1]


def _cfg(problem: str, generations: int, population: int, seed: int = 0, **nsga2) -> ExperimentConfig:
    return load_config(ROOT / "configs" / f"nsga2_{problem}.yaml",
                       {"seed": seed, "nsga2": {"generations": generations, "population": population, **nsga2}})


def _our_hypervolume(tmp_path: Path, problem: str, generations: int, population: int, seed: int) -> float:
    out = tmp_path / f"{problem}_{seed}"
    tune_pareto(_cfg(problem, generations, population, seed), out, progress=False, plots=False)
    front = np.array([[r["f1"], r["f2"]] for r in read_front(out)])
    return hypervolume(front, (1.1, 1.1))


def _pymoo_hypervolume(problem: str, evaluations: int, population: int, seed: int) -> float:
    from pymoo.algorithms.moo.nsga2 import NSGA2
    from pymoo.optimize import minimize
    from pymoo.problems import get_problem

    res = minimize(get_problem(problem), NSGA2(pop_size=population), ("n_evals", evaluations), seed=seed)
    return hypervolume(res.F, (1.1, 1.1))


def _reference_check(tmp_path, problem, generations, population, seeds) -> tuple[float, float]:
    pytest.importorskip("pymoo")
    budget = 2 * population + generations * population  # pygad's initial 2P solutions, then P offspring per generation
    ours = np.mean([_our_hypervolume(tmp_path, problem, generations, population, s) for s in seeds])
    theirs = np.mean([_pymoo_hypervolume(problem, budget, population, s) for s in seeds])
    return ours, theirs


def test_zdt1_hypervolume_reaches_pymoo_small_budget(tmp_path):
    ours, theirs = _reference_check(tmp_path, "zdt1", generations=60, population=40, seeds=(0, 1))
    assert ours >= 0.95 * theirs, (ours, theirs)


@pytest.mark.slow
@pytest.mark.parametrize("problem", ["zdt1", "zdt2"])
def test_zdt_hypervolume_reaches_pymoo_at_the_config_budget(tmp_path, problem):
    """The configs' budget (population 100, 150 generations: 15,200 evaluations), five seeds."""
    ours, theirs = _reference_check(tmp_path, problem, generations=150, population=100, seeds=range(5))
    assert ours >= 0.95 * theirs, (ours, theirs)
    ideal = {"zdt1": 1.21 - 1 / 3, "zdt2": 1.21 - 2 / 3}[problem]  # area under the known front up to (1.1, 1.1)
    assert ours > 0.9 * ideal


def test_fast_non_dominated_sort_equals_pygads():
    ga = GA(num_generations=1, num_parents_mating=2, fitness_func=lambda g, s, i: [0.0, 0.0], sol_per_pop=4,
            num_genes=2, suppress_warnings=True)
    rng = np.random.default_rng(0)
    for trial in range(12):  # continuous values, and small integers (ties, duplicates)
        f = rng.integers(0, 4, size=(50, 2)).astype(float) if trial % 2 else rng.random((50, 2 + trial % 3))
        ours, ours_idx = ga.non_dominated_sorting(f)
        ref, ref_idx = pygad.GA.non_dominated_sorting(ga, f)
        np.testing.assert_array_equal(ours_idx, ref_idx)
        assert len(ours) == len(ref)
        for a, b in zip(ours, ref):
            assert a.shape == b.shape and list(a[:, 0]) == list(b[:, 0])
            assert all(np.array_equal(x, y) for x, y in zip(a[:, 1], b[:, 1]))


def test_hypervolume_matches_pymoo_and_pygad():
    hv_mod = pytest.importorskip("pymoo.indicators.hv")
    rng = np.random.default_rng(1)
    f2 = rng.random((40, 2)) * 1.2  # some points beyond the reference: they add nothing
    assert hypervolume(f2, (1.1, 1.1)) == pytest.approx(hv_mod.HV(ref_point=np.array([1.1, 1.1]))(f2), rel=1e-12)
    f3 = rng.random((25, 3))
    assert hypervolume(f3, (1.0, 1.0, 1.0)) == pytest.approx(hv_mod.HV(ref_point=np.ones(3))(f3), rel=1e-9)
    assert hypervolume(np.array([[2.0, 2.0]]), (1.0, 1.0)) == 0.0
    assert hypervolume(np.array([[0.5, 0.5]]), (1.0, 1.0)) == pytest.approx(0.25)


def test_rank_and_crowding():
    f = np.array([[0.0, 1.0], [0.5, 0.5], [1.0, 0.0], [0.6, 0.6], [1.0, 1.0], [0.2, 0.9]])
    rank, crowd = rank_and_crowding(f)
    np.testing.assert_array_equal(rank, [0, 0, 0, 1, 2, 0])
    assert np.isinf(crowd[[0, 2]]).all() and np.isfinite(crowd[[1, 5]]).all() and crowd[1] > crowd[5]
    np.testing.assert_array_equal(non_dominated(f), rank == 0)
    np.testing.assert_array_equal(pareto_front(f), [0, 5, 1, 2])  # sorted by the first objective


def test_level_selector_follows_eq4_of_paper_002():
    l = np.array([0.0, 0.1, 0.25, 0.2501, 0.5, 0.5001, 0.75, 0.7501, 1.0])
    np.testing.assert_array_equal(level_from_selector(l), [1, 1, 1, 2, 2, 3, 3, 0, 0])
    spec = GenomeSpec((GeneConfig("w_ik", 0.01, 100.0, "log"), GeneConfig("level_ik", type="level"),
                       GeneConfig("kp", 10, 300, "linear", "int"), GeneConfig("x", size=3)))
    assert spec.num_genes == 6 and spec.columns == ["w_ik", "level_ik", "kp", "x[0]", "x[1]", "x[2]"]
    g = spec.decode(np.array([[0.5, 0.6, 0.5, 0.1, 0.2, 0.3]]))[0]
    assert g["w_ik"] == pytest.approx(1.0) and g["level_ik"] == 3 and g["kp"] == 155 and g["x"] == [0.1, 0.2, 0.3]


def test_nsga2_pygad_settings():
    cfg = _cfg("zdt1", generations=7, population=10)
    problem, objective = make_problem(cfg)
    ga = build_ga(problem, cfg, lambda g, s, i: [[0.0, 0.0]] * len(s))
    assert (ga.sol_per_pop, ga.num_parents_mating, ga.keep_elitism, ga.num_offspring) == (20, 10, 10, 10)
    assert ga.parent_selection_type == "nsga2" and ga.select_parents.__name__ == "nsga2_selection"
    assert ga.mutation_type == "polynomial" and ga.mutation_probability == pytest.approx(1 / 30)
    assert ga.num_generations == 7 and objective.objectives == ("f1", "f2") and problem.spec.num_genes == 30


# --------------------------------------------------------------------------------- pluggable objectives
@register("sphere3", objectives=("d0", "d1", "d2"), genes=(GeneConfig("x", -1.0, 1.0, size=4),),
          reference_point=(9.0, 9.0, 9.0))
def sphere3(genomes: list[dict], cfg: ExperimentConfig) -> np.ndarray:
    """Three squared distances to three corners: a 3-objective toy with a known Pareto set (their simplex)."""
    x = np.array([g["x"] for g in genomes])
    corners = np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0]], dtype=float)
    return ((x[:, None, :] - corners[None]) ** 2).sum(-1)


STOP = {"after": None}


@register("zdt1_dies", objectives=("f1", "f2"), genes=(GeneConfig("x", 0.0, 1.0, size=30),))
def zdt1_dies(genomes: list[dict], cfg: ExperimentConfig) -> np.ndarray:
    """ZDT1 that raises KeyboardInterrupt (a Ctrl-C) once STOP['after'] evaluations are spent."""
    if STOP["after"] is not None:
        STOP["after"] -= len(genomes)
        if STOP["after"] < 0:
            raise KeyboardInterrupt
    return get_objective("zdt1").fn(genomes, cfg)


def _rows(out: Path) -> list[list[str]]:
    with (out / "evaluations.csv").open() as f:
        rows = list(csv.reader(f))
    drop = rows[0].index("seconds")
    return [r[:drop] + r[drop + 1:] for r in rows]


def test_resume_after_ctrl_c_equals_an_uninterrupted_run(tmp_path):
    cfg = _cfg("zdt1", generations=8, population=12, objective="test_tuning_nsga2:zdt1_dies")
    tune_pareto(cfg, tmp_path / "full", progress=False, plots=False)
    STOP["after"] = 24 + 12 * 4 + 5
    try:
        with pytest.raises(KeyboardInterrupt):
            tune_pareto(cfg, tmp_path / "cut", progress=False, plots=False)
    finally:
        STOP["after"] = None
    assert read_state(tmp_path / "cut")["generation"] == 4
    tune_pareto(cfg, tmp_path / "cut", resume=True, progress=False, plots=False)
    assert _rows(tmp_path / "cut") == _rows(tmp_path / "full")
    assert (tmp_path / "cut" / "front.csv").read_text() == (tmp_path / "full" / "front.csv").read_text()
    # a finished run resumed for more generations and stopped: its old front is gone, not left to --pick from
    longer = _cfg("zdt1", generations=10, population=12, objective="test_tuning_nsga2:zdt1_dies")
    STOP["after"] = 5
    try:
        with pytest.raises(KeyboardInterrupt):
            tune_pareto(longer, tmp_path / "full", resume=True, progress=False, plots=False)
    finally:
        STOP["after"] = None
    from a3cqp_rl.exceptions import A3CQPError

    with pytest.raises(A3CQPError, match="front.csv not found; has the run finished"):
        pick(tmp_path / "full", 0)


def test_same_front_whatever_the_worker_count(tmp_path):
    cfg = _cfg("zdt2", generations=4, population=10)
    tune_pareto(cfg, tmp_path / "w1", progress=False, plots=False)
    tune_pareto(cfg, tmp_path / "w2", workers=2, progress=False, plots=False)
    assert _rows(tmp_path / "w1") == _rows(tmp_path / "w2")


def test_three_objectives_cli_pick_and_plots(tmp_path):
    from a3cqp_rl.cli import main

    path = tmp_path / "s3.yaml"
    path.write_text(yaml.safe_dump({"nsga2": {"objective": "test_tuning_nsga2:sphere3", "population": 16,
                                              "generations": 10}}))
    out = tmp_path / "run"
    assert main(["pareto", "--config", str(path), "--out", str(out), "--quiet"]) == 0
    for name in ("front.csv", "evaluations.csv", "state.json", "config.yaml", "pareto.png", "pareto_3d.png"):
        assert (out / name).is_file(), name
    front = read_front(out)
    assert 1 <= len(front) <= 16
    values = np.array([[r["d0"], r["d1"], r["d2"]] for r in front])
    assert non_dominated(values).all()
    assert main(["pareto", "--out", str(out), "--pick", "0"]) == 0
    picked = yaml.safe_load((out / "pick_0.yaml").read_text())
    assert picked["objectives"] == {"d0": front[0]["d0"], "d1": front[0]["d1"], "d2": front[0]["d2"]}
    assert picked["genes"]["x"] == [front[0][f"x[{i}]"] for i in range(4)]
    assert main(["pareto", "--out", str(out), "--pick", str(len(front))]) == 2  # out of range: an error
    assert main(["plot", "pareto", str(out), "--out", str(tmp_path / "p.png")]) == 0
    assert (tmp_path / "p.png").is_file() and (tmp_path / "p_3d.png").is_file()
    # more generations on the finished run
    assert main(["pareto", "--out", str(out), "--resume", "--generations", "12", "--quiet"]) == 0
    assert read_state(out)["generation"] == 12


def test_unknown_objective_is_a_config_error(tmp_path):
    with pytest.raises(ConfigError, match="unknown objective 'zdt9'"):
        get_objective("zdt9")
    with pytest.raises(ConfigError, match="cannot import"):
        get_objective("no_such_module:zdt1")


def test_pick_without_a_finished_run_is_an_error(tmp_path):
    from a3cqp_rl.exceptions import A3CQPError

    with pytest.raises(A3CQPError):
        pick(tmp_path, 0)


def test_cli_ctrl_c_says_where_to_resume_and_a_second_writer_is_refused(tmp_path, capsys):
    from a3cqp_rl.cli import main
    from a3cqp_rl.run_folder import RunFolder

    path = tmp_path / "dies.yaml"
    path.write_text(yaml.safe_dump({"nsga2": {"objective": "test_tuning_nsga2:zdt1_dies", "population": 12,
                                              "generations": 8}}))
    out = tmp_path / "run"
    STOP["after"] = 24 + 12 * 4 + 5
    try:
        assert main(["pareto", "--config", str(path), "--out", str(out), "--quiet"]) == 130
    finally:
        STOP["after"] = None
    err = capsys.readouterr().err
    assert f"interrupted after generation 4; {out}/state.json holds it, continue with --resume" in err
    assert "Traceback" not in err
    with RunFolder.open(out, resume=True):  # another process writing the run
        assert main(["pareto", "--out", str(out), "--resume", "--quiet"]) == 2
        assert "being written by another process" in capsys.readouterr().err
    assert read_state(out)["generation"] == 4  # untouched by the refused writer
    assert main(["pareto", "--out", str(out), "--resume", "--quiet"]) == 0
    assert read_state(out)["generation"] == 8


@pytest.mark.parametrize("command, config, match", [
    ("pareto", "configs/ga_point_mass.yaml", "is a GA config .* run it with a3cqp tune"),
    ("pareto", "configs/point_mass_a2c.yaml", "has no nsga2: section"),
    ("tune", "configs/nsga2_zdt1.yaml", "is an NSGA-II config .* run it with a3cqp pareto"),
])
def test_a_tuner_refuses_the_other_tuners_config(tmp_path, capsys, command, config, match):
    from a3cqp_rl.cli import main

    out = tmp_path / "o"
    assert main([command, "--config", str(ROOT / config), "--generations", "1", "--out", str(out), "--quiet"]) == 2
    assert re.search(match, capsys.readouterr().err)
    assert not out.exists()


def test_tuner_output_paths_are_checked_before_any_work(tmp_path, capsys):
    from a3cqp_rl.cli import main

    afile = tmp_path / "afile"
    afile.write_text("")
    for out, said in ((afile, "is a file, expected a folder"), (afile / "x", "is a file, not a folder")):
        assert main(["pareto", "--generations", "1", "--population", "8", "--out", str(out), "--quiet"]) == 2
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err
    assert main(["pareto", "--config", str(tmp_path), "--out", str(tmp_path / "o")]) == 2
    assert "is a folder, expected a YAML config file" in capsys.readouterr().err


def test_tuners_take_set_overrides_kept_in_the_run_and_refused_on_a_different_resume(tmp_path, capsys):
    from a3cqp_rl.cli import main

    out = tmp_path / "run"
    assert main(["pareto", "--config", str(ROOT / "configs" / "nsga2_zdt1.yaml"), "--out", str(out), "--quiet",
                 "--set", "nsga2.population=8", "--set", "seed=3", "--set", "nsga2.generations=5",
                 "--generations", "1"]) == 0  # the flag wins over a --set of the same key
    saved = yaml.safe_load((out / "config.yaml").read_text())
    assert (saved["nsga2"]["population"], saved["seed"], saved["nsga2"]["generations"]) == (8, 3, 1)
    assert read_state(out)["generation"] == 1
    # a resume under another setting would mix two runs' evaluations
    assert main(["pareto", "--out", str(out), "--resume", "--quiet", "--set", "seed=4"]) == 2
    assert "with a different config (seed: 3 -> 4)" in capsys.readouterr().err
    assert main(["pareto", "--out", str(out), "--resume", "--quiet", "--set", "nsga2.generations=2"]) == 0
    assert read_state(out)["generation"] == 2
    for argv, said in ((["--set", "nsga2.population=-1"], "population"), (["--set", "nope"], "expected KEY=VALUE"),
                       (["--out", str(out), "--pick", "0", "--set", "seed=1"], "--set applies to a run"),
                       (["--out", str(out), "--pick", "0", "--resume", "--generations", "5"],
                        "--resume, --generations apply to a run")):
        assert main(["pareto", *argv, "--quiet"]) == 2
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err
    tune_out = tmp_path / "ga"
    assert main(["tune", "--out", str(tune_out), "--set", "ga.num_generations=-2", "--quiet"]) == 2
    assert "num_generations" in capsys.readouterr().err and not (tune_out / "state.json").exists()
    # counts are refused by argparse, before a folder is made or a progress bar drawn
    for cmd, flag in (("tune", "--workers"), ("tune", "--generations"), ("pareto", "--workers"),
                      ("pareto", "--population")):
        with pytest.raises(SystemExit) as exc:
            main([cmd, "--out", str(tmp_path / "never"), flag, "0", "--quiet"])
        assert exc.value.code == 2 and f"argument {flag}: must be an integer >= 1, got 0" in capsys.readouterr().err
        assert not (tmp_path / "never").exists()


def test_a_stop_within_a_generation_keeps_its_finished_chunks_for_the_resume(tmp_path, capsys):
    from a3cqp_rl.cli import main

    cfg = _cfg("zdt1", generations=3, population=12, objective="test_tuning_nsga2:zdt1_dies", chunk_size=3)
    tune_pareto(cfg, tmp_path / "full", progress=False, plots=False)
    for after, gen in ((7, None), (24 + 12 + 7, 1)):  # within the initial population; within a later generation
        cut = tmp_path / f"cut_{after}"
        STOP["after"] = after
        try:
            with pytest.raises(KeyboardInterrupt):
                tune_pareto(cfg, cut, progress=False, plots=False)
        finally:
            STOP["after"] = None
        kept = len((cut / "pending.csv").read_text().splitlines()) - 1
        assert kept > 0 and kept % 3 == 0  # whole chunks of three, as they finished
        if gen is None:
            assert kept == 6 and not (cut / "state.json").exists()
        else:
            assert read_state(cut)["generation"] >= gen
        res = tune_pareto(cfg, cut, resume=True, progress=False, plots=False)
        assert _rows(cut) == _rows(tmp_path / "full") and not (cut / "pending.csv").exists()
        assert res.evaluations == read_state(tmp_path / "full")["evaluations"]  # the kept six not evaluated again
    # the command says what it kept, and SIGTERM is a stop like Ctrl-C
    path = tmp_path / "dies.yaml"
    path.write_text(yaml.safe_dump({"nsga2": {"objective": "test_tuning_nsga2:zdt1_dies", "population": 12,
                                              "generations": 3, "chunk_size": 3}}))
    STOP["after"] = 7
    try:
        assert main(["pareto", "--config", str(path), "--out", str(tmp_path / "cli"), "--quiet"]) == 130
    finally:
        STOP["after"] = None
    err = capsys.readouterr().err
    assert "interrupted within the initial population; 6 genome(s) evaluated are kept in" in err
    assert main(["pareto", "--out", str(tmp_path / "cli"), "--resume", "--quiet"]) == 0
    assert read_state(tmp_path / "cli")["generation"] == 3


def test_sigterm_stops_a_tuner_as_ctrl_c_does(tmp_path, capsys, monkeypatch):
    import os
    import signal

    from a3cqp_rl.cli import main
    from algorithms.tuning import runner

    calls = {"n": 0}
    real = runner._evaluate_chunk

    def term_after_two(*args):  # noqa: ANN002, ANN202
        calls["n"] += 1
        if calls["n"] == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return real(*args)

    monkeypatch.setattr(runner, "_evaluate_chunk", term_after_two)
    path = tmp_path / "z.yaml"
    path.write_text(yaml.safe_dump({"nsga2": {"objective": "zdt1", "population": 12, "generations": 3,
                                              "chunk_size": 3}}))
    assert main(["pareto", "--config", str(path), "--out", str(tmp_path / "run"), "--quiet"]) == 143
    assert "interrupted within the initial population" in capsys.readouterr().err
    assert signal.getsignal(signal.SIGTERM) is not runner.stop_on_sigterm._raise  # the handler is put back
