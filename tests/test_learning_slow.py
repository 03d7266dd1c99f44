"""Slow: a full 1e6-step training learns the paper's Fig. 5 regions (run with `pytest -m slow`)."""

from pathlib import Path

import pytest

from a3cqp_rl.config import load_config
from a3cqp_rl.regions import check_fig5_regions
from algorithms.a2c import load_policy, train

CONFIGS = Path(__file__).parents[1] / "configs"


@pytest.mark.slow
@pytest.mark.xfail(reason="not reproduced yet: no setting found passes all 4 Fig. 5 region checks in 1e6 steps "
                          "(see configs/point_mass_a2c_tuned.yaml and the README); the check stays so it reports when it does",
                   strict=False)
def test_tuned_config_learns_fig5_regions(tmp_path):
    cfg = load_config(CONFIGS / "point_mass_a2c_tuned.yaml")
    res = train(cfg, tmp_path, total_steps=1_000_000)
    results = check_fig5_regions(load_policy(res.policy_path))
    assert all(r.ok for r in results), results
