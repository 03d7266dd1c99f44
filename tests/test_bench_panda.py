"""bench/panda_env.py times what it says: the peg-in-hole env with every peg on the block (timings are not asserted)."""

from __future__ import annotations

import math

from bench.panda_env import parked_cost, run_env, run_parked


def test_the_panda_benchmark_times_arms_in_contact() -> None:
    r = run_env(2, 5)
    assert r["contacts"] >= 1.0  # MuJoCo contacts per arm over the timed steps: the pegs press on the block
    assert r["steps_s"] > 0.0 and r["rtf"] > 0.0


def test_the_benchmarks_numpy_peer_runs_the_numpy_sensing_and_restores_the_c_one() -> None:
    from a3cqp_rl.robot import PandaSim, sense

    native = sense._library.get() is not None
    with sense.numpy_sensing():
        assert PandaSim(1, tool="peg")._native_observe is None
        assert sense._library.get() is None
    assert (PandaSim(1, tool="peg")._native_observe is not None) == native


def test_the_benchmark_times_parked_and_live_arms() -> None:
    """The parked-arm line measures a cost per arm and period for each (differences of wall times, so either can
    come out at ~0 or below in a short run on a busy machine: finite is what is asserted, the ratio is printed)."""
    assert run_parked(3, 2, 1) > 0.0
    parked, live = parked_cost(4, 2, 2, 1)
    assert math.isfinite(parked) and math.isfinite(live)


def test_the_benchmarks_python_period_peer_runs_the_python_period() -> None:
    from envs.native import tick
    from envs.panda import PandaEnv

    native = tick._library.get() is not None
    with tick.numpy_tick():
        assert PandaEnv(1)._native_tick is None
    assert (PandaEnv(1)._native_tick is not None) == native


def test_the_bench_command_names_an_unknown_benchmark_and_checks_the_panda_arguments_first(capsys) -> None:  # noqa: ANN001
    import pytest

    from a3cqp_rl.bench_cli import main as bench_main

    assert bench_main(["nonexistent"]) == 2
    assert "no benchmark named 'nonexistent'" in capsys.readouterr().err
    for args, says in ((["--sizes", "0"], "--sizes and --repeats must be >= 1"),
                       (["--repeats", "0"], "--sizes and --repeats must be >= 1"),
                       (["--eval", "/nonexistent/policy.pt"], "no such policy file"),
                       (["--eval-all"], "--eval-all needs --eval")):
        with pytest.raises(SystemExit):
            bench_main(["panda", "--quick", *args])
        err = capsys.readouterr().err
        assert says in err and "usage: a3cqp bench panda" in err


def test_bench_all_help_lists_every_benchmark_and_runs_none(capsys) -> None:  # noqa: ANN001
    from a3cqp_rl.bench_cli import BENCHES
    from a3cqp_rl.bench_cli import main as bench_main

    assert bench_main(["all", "--help"]) == 0
    out = capsys.readouterr().out
    assert "===" not in out and all(name in out for name in BENCHES)
