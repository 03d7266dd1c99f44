"""Many C A2C iterations per call (`FusedRollout.iterate_many`) give the numbers one call per iteration gave."""

import json
import math

import pytest
import torch

from algorithms import native
from algorithms.a2c import FusedRollout, _randn_splits
from tests.a2c_reference_cases import CASES, REFERENCE, compiler, compute

pytestmark = pytest.mark.skipif(native.load() is None, reason="no C compiler: the torch path runs (warned)")

_STORED = json.loads(REFERENCE.read_text())


def _same(a: dict, b: dict) -> bool:
    """Digests equal, NaN equal to NaN (region columns of runs without region checks); the last log row on the
    columns `b` has (the stored rows predate the transfer columns, which follow from the parameters compared)."""
    def norm(v):
        return "nan" if isinstance(v, float) and math.isnan(v) else v
    keys = b["final_metrics"].keys()
    return {k: norm(a["final_metrics"].get(k)) for k in keys} == {k: norm(b["final_metrics"][k]) for k in keys} \
        and {k: v for k, v in a.items() if k != "final_metrics"} == {k: v for k, v in b.items() if k != "final_metrics"}


@pytest.mark.parametrize("name", list(CASES))
def test_runs_match_the_stored_per_iteration_results(name):
    """Each case's parameters, averaged policy, every episode return and last log row are those the per-iteration C
    code computed (bit for bit with the compiler that stored them; within float32 round-off elsewhere)."""
    got, ref = compute(name), _STORED["cases"][name]
    if compiler() == _STORED["compiler"]:
        assert _same(got, ref), {k: (got[k], ref[k]) for k in got if got[k] != ref[k]}
    else:
        assert got["episodes"] == ref["episodes"]
        assert got["mean_return"] == pytest.approx(ref["mean_return"], rel=1e-3)


@pytest.mark.parametrize("name", ["ga_n1", "options"])
def test_many_per_call_equals_one_per_call(name, monkeypatch):
    """Same build, the two loop shapes: every update its own call vs batches up to log rows and episode ends."""
    calls = []
    many = FusedRollout.iterate_many

    def counting(self, count, *args):
        calls.append(count)
        return many(self, count, *args)

    monkeypatch.setattr(FusedRollout, "iterate_many", counting)
    batched = compute(name)
    assert max(calls) > 1  # the batched path did run
    monkeypatch.setattr(FusedRollout, "max_updates", lambda self: 1)
    calls.clear()
    single = compute(name)
    assert max(calls) == 1
    assert _same(batched, single)


@pytest.mark.parametrize("rows, cols", [(1, 4), (4, 4), (17, 4), (18, 4), (32, 4), (33, 64), (300, 4)])
def test_outer_sum_adds_as_torch(rows, cols):
    """The C rollout sum reproduces torch's x.sum(0) (its blocked order from 18 rows on) bit for bit."""
    assert native.outer_sum_matches_torch(native.load(), rows, cols)


def test_outer_sum_check_can_fail():
    """The check sees a different order: torch adds 1, 2, 5 or 8 columns its own way from 5 rows on (such trainers
    keep one C call per iteration)."""
    assert not native.outer_sum_matches_torch(native.load(), 40, 1)
    assert not native.outer_sum_matches_torch(native.load(), 8, 8)


def test_noise_split_check():
    """16 values per update split exactly (torch's blocks of 16); 12 per update do not."""
    assert _randn_splits(1, (4, 4)) and _randn_splits(3, (16, 4))
    assert not _randn_splits(1, (3, 4))


def test_iterate_many_refuses_to_cross_an_episode_end():
    """More iterations than remain before the next episode end is an error, not a silent reorder of the RNG."""
    from a3cqp_rl.config import config_from_dict
    from algorithms.make_env import make_env
    from algorithms.networks import ParamLayout

    cfg = config_from_dict({"a2c": {"n_steps": 4, "num_envs": 4, "compile": False}, "point_mass": {"episode_steps": 40}})
    env = make_env(cfg)
    layout = ParamLayout(3, 4, cfg.a2c.hidden, cfg.a2c.network, 3)
    gen = torch.Generator().manual_seed(0)
    flat = layout.init(gen, 0.0)
    runner = FusedRollout(env, layout, gen, cfg.a2c)
    assert runner.max_updates() == 10
    with pytest.raises(ValueError, match="cross an episode end"):
        runner.iterate_many(11, flat, torch.full_like(flat, 0.0), torch.zeros(5))
    runner.iterate_many(10, flat, torch.full_like(flat, 0.0), torch.zeros(5))
    assert len(runner.finished) == 4 and runner.max_updates() == 10
