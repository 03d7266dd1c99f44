"""Smoke test of bench/qp.py: runs on a tiny batch and prints the table (timings are not asserted)."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

import pytest

BENCH = Path(__file__).resolve().parents[1] / "bench" / "qp.py"


def test_bench_qp_main_runs(capsys) -> None:
    spec = importlib.util.spec_from_file_location("bench_qp", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # dataclasses resolve their module through sys.modules
    spec.loader.exec_module(module)
    rc = module.main(["--batches", "3", "--skip", "cvxpylayers", "qpth", "osqp", "proxsuite"])
    out = capsys.readouterr().out
    assert rc == 0
    assert "| a3cqp_rl.qp (cold) | 3 |" in out and "| a3cqp_rl.qp (warm) | 3 |" in out
    # our accuracy column is filled and within 1e-6 of Clarabel
    row = next(line for line in out.splitlines() if line.startswith("| a3cqp_rl.qp (cold) | 3 |"))
    assert float(row.split("|")[-2]) <= 1e-6


@pytest.mark.slow
def test_bench_qp_check_mode_prints_the_family_tables(capsys) -> None:
    spec = importlib.util.spec_from_file_location("bench_qp_check", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    assert module.main(["--check", "--sweep", "2"]) == 0
    out = capsys.readouterr().out
    assert "| LP |" in out and "| invalid |" in out and "Random family members" in out
    rows = [line.split("|") for line in out.splitlines() if line.startswith("| ") and "family" not in line]
    assert rows and all(int(r[4]) == 0 for r in rows)  # no silent wrong answer anywhere


def test_bench_qp_blocks_mode_prints_every_variant_against_daqp(capsys) -> None:
    pytest.importorskip("daqp")
    spec = importlib.util.spec_from_file_location("bench_qp_blocks", BENCH)
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    assert module.main(["--blocks", "--quick"]) == 0
    out = capsys.readouterr().out
    lines = [line for line in out.splitlines() if "x DAQP" in line]
    assert len(lines) == 5 and "1.00x DAQP" in lines[0] and "qp_vjp" in out
