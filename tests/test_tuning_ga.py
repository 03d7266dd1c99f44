"""The Table V GA on pygad: settings on the pygad instance, learning on a toy fitness with a known best gene,
resume = uninterrupted, worker-count independence, best.yaml accepted by training, clear config errors."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from a3cqp_rl.config import ExperimentConfig, config_to_dict, load_config
from a3cqp_rl.exceptions import CheckpointError, ConfigError
from algorithms.tuning import ga as ga_mod
from algorithms.tuning.ga import make_problem, trial_config, tune, write_best
from algorithms.tuning.runner import build_ga, read_state

ROOT = Path(__file__).resolve().parents[1]
GA_CONFIG = ROOT / "configs" / "ga_point_mass.yaml"
BEST_LR = 1e-3


def toy_fitness(genomes: list[dict], cfg: ExperimentConfig) -> np.ndarray:
    """Known optimum: only the learning rate matters, best at 1e-3 (peak 0 in log10 distance)."""
    return np.array([[-(math.log10(g["learning_rate"]) - math.log10(BEST_LR)) ** 2] for g in genomes])


class Killed(Exception):
    """Stands in for a kill signal in the middle of a generation."""


CALLS = {"left": None}


def dying_fitness(genomes: list[dict], cfg: ExperimentConfig) -> np.ndarray:
    """toy_fitness that raises Killed once CALLS['left'] evaluations are spent."""
    if CALLS["left"] is not None:
        CALLS["left"] -= len(genomes)
        if CALLS["left"] < 0:
            raise Killed
    return toy_fitness(genomes, cfg)


def _cfg(generations: int, **ga) -> ExperimentConfig:
    return load_config(GA_CONFIG, {"ga": {"num_generations": generations, **ga}})


def _rows(out: Path) -> list[list[str]]:
    """evaluations.csv without the timing column."""
    with (out / "evaluations.csv").open() as f:
        rows = list(csv.reader(f))
    drop = rows[0].index("seconds")
    return [r[:drop] + r[drop + 1:] for r in rows]


def test_table_v_settings_on_the_pygad_instance():
    cfg = load_config(GA_CONFIG)
    assert config_to_dict(cfg.ga) == config_to_dict(ExperimentConfig().ga)  # the YAML spells out the defaults
    problem = make_problem(cfg)
    ga = build_ga(problem, cfg, lambda g, s, i: [0.0] * len(s))
    assert (ga.num_generations, ga.sol_per_pop, ga.num_parents_mating, ga.num_genes) == (50, 8, 4, 5)
    assert ga.parent_selection_type == "sss" and ga.select_parents.__name__ == "steady_state_selection"
    assert (ga.keep_parents, ga.keep_elitism) == (1, 0)  # keep_elitism > 0 would override keep_parents in pygad
    assert ga.crossover_type == "single_point" and ga.crossover.__name__ == "single_point_crossover"
    assert ga.mutation_type == "random" and ga.mutation.__name__ == "random_mutation"
    assert ga.mutation_percent_genes == 10 and ga.mutation_num_genes == 1 and ga.num_offspring == 7
    assert problem.spec.columns == ["learning_rate", "ent_coef", "n_steps", "rms_eps", "max_grad_norm"]


def test_genes_decode_to_their_ranges():
    spec = make_problem(load_config(GA_CONFIG)).spec
    lo, hi = spec.decode(np.array([[0.0] * 5, [1.0] * 5]))
    assert lo == {"learning_rate": 1e-6, "ent_coef": 1e-6, "n_steps": 1, "rms_eps": 1e-8, "max_grad_norm": 0.1}
    assert hi["learning_rate"] == pytest.approx(1e-2) and hi["n_steps"] == 32 and isinstance(hi["n_steps"], int)
    mid = spec.decode(np.full((1, 5), 0.5))[0]
    assert mid["learning_rate"] == pytest.approx(1e-4) and mid["max_grad_norm"] == pytest.approx(1.0)  # log scale


def test_toy_problem_improves_and_finds_the_known_best_gene(tmp_path):
    res = tune(_cfg(25), tmp_path / "ga", fitness=toy_fitness, progress=False, plots=False)
    fit = np.array([r["fitness"] for r in res.rows])
    gen = np.array([r["generation"] for r in res.rows])
    assert fit[gen == 25].max() > fit[gen == 0].max()  # learned something
    best = max(res.rows, key=lambda r: r["fitness"])
    assert abs(math.log10(best["learning_rate"]) - math.log10(BEST_LR)) < 0.3  # within a factor 2 of the optimum
    assert np.all(np.diff([fit[gen == g].max() for g in range(26)]) >= 0)  # steady-state keeps the best parent
    assert len(res.rows) == 26 * 8 and res.generation == 25
    best_yaml = load_config(tmp_path / "ga" / "best.yaml")
    assert best_yaml.a2c.learning_rate == best["learning_rate"] and best_yaml.a2c.n_steps == int(best["n_steps"])


def test_resume_after_a_kill_equals_an_uninterrupted_run(tmp_path):
    full = tune(_cfg(6), tmp_path / "full", fitness=toy_fitness, progress=False, plots=False)
    CALLS["left"] = 8 + 7 * 3 + 2  # generations 0-3 finish; the kill comes during generation 4
    try:
        with pytest.raises(Killed):
            tune(_cfg(6), tmp_path / "killed", fitness=dying_fitness, progress=False, plots=False)
    finally:
        CALLS["left"] = None
    assert read_state(tmp_path / "killed")["generation"] == 3
    with pytest.raises(CheckpointError, match="--resume"):  # no silent overwrite of a run
        tune(_cfg(6), tmp_path / "killed", fitness=toy_fitness, progress=False, plots=False)
    res = tune(_cfg(6), tmp_path / "killed", fitness=toy_fitness, resume=True, progress=False, plots=False)
    assert res.resumed_from == 3 and res.generation == 6
    np.testing.assert_array_equal(res.values, full.values)
    assert res.genes == full.genes
    assert _rows(tmp_path / "killed") == _rows(tmp_path / "full")
    assert res.evaluations == full.evaluations  # the cache reused every logged evaluation
    # a finished run can be continued for more generations: the same as running them in one go
    longer = tune(_cfg(9), tmp_path / "full", fitness=toy_fitness, resume=True, progress=False, plots=False)
    straight = tune(_cfg(9), tmp_path / "straight", fitness=toy_fitness, progress=False, plots=False)
    assert _rows(tmp_path / "full") == _rows(tmp_path / "straight") and longer.genes == straight.genes


def test_resume_drops_rows_a_kill_left_after_the_checkpoint_and_checks_the_config(tmp_path):
    tune(_cfg(2), tmp_path / "r", fitness=toy_fitness, progress=False, plots=False)
    before = _rows(tmp_path / "r")
    with (tmp_path / "r" / "evaluations.csv").open("a") as f:  # a kill between the rows and state.json
        f.write("3,0,0.001,0.001,4,1e-05,1.0,-0.5,1.0,1\n")
    tune(_cfg(2), tmp_path / "r", fitness=toy_fitness, resume=True, progress=False, plots=False)
    assert _rows(tmp_path / "r") == before
    with pytest.raises(ConfigError, match="steps_per_trial"):
        tune(_cfg(2, steps_per_trial=1000), tmp_path / "r", fitness=toy_fitness, resume=True, progress=False)


def test_same_result_whatever_the_worker_count(tmp_path):
    one = tune(_cfg(3), tmp_path / "w1", fitness=toy_fitness, workers=1, progress=False, plots=False)
    two = tune(_cfg(3), tmp_path / "w2", fitness=toy_fitness, workers=2, progress=False, plots=False)
    assert _rows(tmp_path / "w1") == _rows(tmp_path / "w2")
    np.testing.assert_array_equal(one.values, two.values)


def test_longest_trainings_start_first_and_results_do_not_depend_on_it(tmp_path, monkeypatch):
    """The pool gets the genomes with the smallest n (the longest trainings) first; the run is the same as in
    population order."""
    cfg = _cfg(3)
    assert ga_mod.trial_cost(cfg, {"n_steps": 1}) > ga_mod.trial_cost(cfg, {"n_steps": 4}) > ga_mod.trial_cost(cfg, {"n_steps": 32})
    from algorithms.tuning.pool import SerialPool

    dispatched = []
    imap = SerialPool.imap

    def recording(self, fn, chunks, args=()):
        dispatched.append([c[0]["n_steps"] for c in chunks])
        return imap(self, fn, chunks, args)

    monkeypatch.setattr(SerialPool, "imap", recording)
    by_cost = tune(cfg, tmp_path / "cost", fitness=toy_fitness, progress=False, plots=False)
    assert all(order == sorted(order) for order in dispatched) and any(len(set(o)) > 1 for o in dispatched)
    monkeypatch.setattr(ga_mod, "trial_cost", lambda cfg, genes: 1.0)  # all equal: population order
    dispatched.clear()
    in_order = tune(cfg, tmp_path / "order", fitness=toy_fitness, progress=False, plots=False)
    assert any(order != sorted(order) for order in dispatched)
    assert _rows(tmp_path / "cost") == _rows(tmp_path / "order")
    np.testing.assert_array_equal(by_cost.values, in_order.values)


def test_real_trainings_end_to_end_and_best_yaml_trains(tmp_path):
    """Eq. 34 on real (tiny) trainings; `a3cqp train --config best.yaml` accepts the result."""
    cfg = _cfg(1, steps_per_trial=4000, fitness_episodes=5)
    res = tune(cfg, tmp_path / "ga", progress=False)
    fit = [r["fitness"] for r in res.rows]
    assert all(-(0.5 + 20 + 1) * 500 <= f <= 2 * 500 for f in fit) and len(set(fit)) > 1
    assert (tmp_path / "ga" / "ga.png").stat().st_size > 10_000
    from algorithms.train import main as train_main

    rc = train_main(["--config", str(tmp_path / "ga" / "best.yaml"), "--steps", "2000", "--out", str(tmp_path / "t"),
                     "--no-plots", "--quiet"])
    assert rc == 0 and (tmp_path / "t" / "policy.pt").is_file()
    trained = yaml.safe_load((tmp_path / "t" / "config.yaml").read_text())
    best = max(res.rows, key=lambda r: r["fitness"])
    assert trained["a2c"]["learning_rate"] == best["learning_rate"] and "ga" not in yaml.safe_load(
        (tmp_path / "ga" / "best.yaml").read_text())


def test_eq34_is_the_mean_of_the_last_n_returns_and_divergence_scores_the_floor(monkeypatch):
    cfg = _cfg(1, fitness_episodes=3, trials=2)

    class Result:
        episode_returns = [-900.0, -10.0, -20.0, -30.0]

    seeds = []

    def fake_train(tc, out=None):
        seeds.append(tc.seed)
        assert tc.a2c.total_steps == cfg.ga.steps_per_trial and tc.a2c.learning_rate == 1e-3
        return Result

    monkeypatch.setattr(ga_mod, "_train", fake_train)
    genes = {"learning_rate": 1e-3, "ent_coef": 1e-4, "n_steps": 4, "rms_eps": 1e-5, "max_grad_norm": 1.0}
    assert ga_mod.episode_reward([genes], cfg)[0, 0] == pytest.approx(-20.0)
    assert seeds == [0, 1]  # ga.trials seeds

    def diverging(tc, out=None):
        raise FloatingPointError("training diverged")

    monkeypatch.setattr(ga_mod, "_train", diverging)
    assert ga_mod.episode_reward([genes], cfg)[0, 0] == -(0.5 + 20.0 + 1.0) * 500  # eq. 30 penalties at their bounds


def test_trial_config_sets_any_experiment_field():
    cfg = load_config(GA_CONFIG, {"ga": {"genes": [{"name": "point_mass.c_d", "low": 1, "high": 9},
                                                   {"name": "gamma", "low": 0.9, "high": 0.999}]}})
    tc = trial_config(cfg, {"point_mass.c_d": 7.5, "gamma": 0.95}, seed=4)
    assert (tc.point_mass.c_d, tc.a2c.gamma, tc.seed, tc.a2c.total_steps) == (7.5, 0.95, 4, cfg.ga.steps_per_trial)


@pytest.mark.parametrize("genes, match", [
    ([{"name": "learnin_rate", "low": 1e-5, "high": 1e-3}], "ga.genes.0..name: unknown a2c field 'learnin_rate'"),
    ([{"name": "gamma", "low": 0.9, "high": 1.5}], r"ga.genes.0..high: 1.5 is not a valid a2c.gamma"),
    ([{"name": "learning_rate", "low": 1e-3, "high": 1e-5}], r"ga.genes.0..low: the range .* need low < high"),
    ([{"name": "learning_rate", "low": 0.0, "high": 1e-3, "scale": "log"}], "log-scale gene needs low > 0"),
    ([{"name": "n_steps", "low": 1, "high": 8}], "a2c.n_steps is an integer: set type: int"),
    ([{"name": "hidden", "low": 1, "high": 8}], "not a number"),
    ([{"name": "reward.alpha", "low": 1, "high": 8}], "not a number"),
])
def test_bad_genes_are_clear_config_errors(tmp_path, genes, match):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"ga": {"genes": genes}}))
    with pytest.raises(ConfigError, match=match):
        load_config(path)


def test_cli_error_is_one_line(tmp_path, capsys):
    path = tmp_path / "bad.yaml"
    path.write_text(yaml.safe_dump({"ga": {"genes": [{"name": "learnin_rate", "low": 1e-5, "high": 1e-3}],
                                           "fitness": "episode_reward"}}))
    from a3cqp_rl.cli import main

    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "learnin_rate" in err and "Traceback" not in err
    path.write_text(yaml.safe_dump({"ga": {"fitness": "speed"}}))
    assert main(["tune", "--config", str(path), "--out", str(tmp_path / "o"), "--quiet"]) == 2
    assert "unknown fitness 'speed'" in capsys.readouterr().err


def test_plot_ga_cli(tmp_path):
    tune(_cfg(2), tmp_path / "ga", fitness=toy_fitness, progress=False, plots=False)
    from a3cqp_rl.cli import main

    assert main(["plot", "ga", str(tmp_path / "ga"), "--out", str(tmp_path / "g.png")]) == 0
    assert (tmp_path / "g.png").stat().st_size > 10_000
    assert main(["plot", "pareto", str(tmp_path / "ga")]) == 2  # not an NSGA-II run: an error, no traceback


def test_behaviour_fitness_trains_and_evaluates(tmp_path):
    cfg = _cfg(1, steps_per_trial=2000, fitness="behaviour")
    genes = make_problem(cfg).spec.decode(np.full((1, 5), 0.5))
    value = ga_mod.behaviour(genes, cfg)
    assert value.shape == (1, 1) and np.isfinite(value).all()


def test_write_best_names_the_run(tmp_path):
    res = tune(_cfg(1), tmp_path / "ga", fitness=toy_fitness, progress=False, plots=False)
    text = write_best(_cfg(1), res, tmp_path / "b.yaml").read_text()
    assert text.startswith("# Best of the GA run in") and "learning_rate =" in text


@pytest.mark.slow
def test_ray_tasks_give_the_same_result_as_local_workers(tmp_path):
    """A local Ray instance (2 CPUs) runs the trials: the same evaluations as local worker processes."""
    ray = pytest.importorskip("ray")
    local = tune(_cfg(2), tmp_path / "local", fitness=toy_fitness, workers=2, progress=False, plots=False)
    path = f"{ROOT}:{Path(__file__).parent}"  # this checkout and this test module (toy_fitness) for the workers
    ray.init(num_cpus=2, include_dashboard=False, runtime_env={"env_vars": {"PYTHONPATH": path}})
    try:
        remote = tune(_cfg(2), tmp_path / "ray", fitness=toy_fitness, ray="auto", progress=False, plots=False)
    finally:
        ray.shutdown()
    assert _rows(tmp_path / "ray") == _rows(tmp_path / "local")
    np.testing.assert_array_equal(remote.values, local.values)


def test_a_trial_too_short_for_an_episode_is_refused_before_training(tmp_path, capsys):
    from a3cqp_rl.cli import main

    out = tmp_path / "o"
    assert main(["tune", "--steps-per-trial", "100", "--generations", "1", "--out", str(out), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "ends no training episode" in err and "give at least 2,000" in err and "Traceback" not in err
    assert not out.exists()  # refused before the run folder was made
    cfg = load_config(ROOT / "configs" / "ga_point_mass.yaml", {"ga": {"steps_per_trial": 100}})
    with pytest.raises(ConfigError, match="ends no training episode"):
        make_problem(cfg)
    genes = [{"name": "num_envs", "low": 1, "high": 8, "type": "int"}]
    short = load_config(ROOT / "configs" / "ga_point_mass.yaml", {"ga": {"steps_per_trial": 600, "genes": genes}})
    make_problem(short)  # one env finishes an episode in 600 steps: a genome can score


def _sigint_self(chunk, *args):
    import os
    import signal

    os.kill(os.getpid(), signal.SIGINT)
    return chunk


def test_a_worker_hit_by_ctrl_c_stops_without_a_traceback(capfd):
    from algorithms.tuning.pool import ProcessPool

    pool = ProcessPool(1)
    try:
        with pytest.raises(SystemExit):
            list(pool.imap(_sigint_self, [[1]]))
    finally:
        pool.close()
    assert "KeyboardInterrupt" not in capfd.readouterr().err


def _imported(chunk, *args):
    import sys

    return [name in sys.modules for name in chunk]


def test_local_workers_import_the_preloaded_modules_before_their_first_task():
    from algorithms.tuning.pool import ProcessPool

    pool = ProcessPool(1, preload=("wave",))  # a module nothing else here imports
    try:
        ((_, found, _),) = list(pool.imap(_imported, [["wave", "aifc"]]))
    finally:
        pool.close()
    assert found == [True, False]


def test_resume_of_a_folder_without_a_run_says_so(tmp_path, capsys):
    from algorithms.tuning import nsga2

    for command in (ga_mod.main, nsga2.main):
        assert command(["--out", str(tmp_path / "empty"), "--resume", "--quiet"]) == 2
        err = capsys.readouterr().err
        assert f"no tuning run in {tmp_path / 'empty'} to resume" in err and "Traceback" not in err
