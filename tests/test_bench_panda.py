"""bench/panda_env.py times what it says: the peg-in-hole env with every peg on the block (timings are not asserted)."""

from __future__ import annotations

from bench.panda_env import run_env


def test_the_panda_benchmark_times_arms_in_contact() -> None:
    r = run_env(2, 5)
    assert r["contacts"] >= 1.0  # MuJoCo contacts per arm over the timed steps: the pegs press on the block
    assert r["steps_s"] > 0.0 and r["rtf"] > 0.0
