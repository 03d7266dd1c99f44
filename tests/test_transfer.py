"""The Panda transfer checks of a point-mass policy (a3cqp_rl.transfer) and `a2c.select_policy: transfer`."""

import csv
import math
from types import SimpleNamespace

import pytest
import torch

from a3cqp_rl.adaptation import integrate_weights
from a3cqp_rl.config import A2CConfig, config_from_dict
from a3cqp_rl.exceptions import ConfigError
from a3cqp_rl.transfer import (FREE_MOTION_E, GUIDED_OBS, free_motion_rates, guided_rates, raises_ik,
                               transfer_margin, yields)
from algorithms.a2c import load_policy, train
from algorithms.a2c_run import TransferSelection
from algorithms.networks import ParamLayout


def _stub(free: list[float], guided: list[float]):
    """A policy whose mean action is `free` without force and `guided` under the operator's force."""
    def policy(obs: torch.Tensor) -> torch.Tensor:
        pushed = (obs[:, 2] > 0).unsqueeze(-1)
        return torch.where(pushed, torch.tensor(guided), torch.tensor(free))
    return policy


def test_rates_are_mean_actions_at_the_pandas_free_motion_and_under_the_operator():
    seen = []

    def policy(obs):
        seen.append(obs.clone())
        return obs[:, [0, 2, 1, 0]] * torch.tensor([1.0, 2.0, 3.0, -1.0])

    free, guided = free_motion_rates(policy), guided_rates(policy)
    assert seen[0][:, 0].tolist() == pytest.approx(list(FREE_MOTION_E)) and not seen[0][:, 1:].any()
    assert torch.allclose(seen[1], torch.tensor(GUIDED_OBS))
    e_mean = sum(FREE_MOTION_E) / len(FREE_MOTION_E)
    assert free == pytest.approx([e_mean, 0.0, 0.0, -e_mean])
    f_mean = sum(o[2] for o in GUIDED_OBS) / len(GUIDED_OBS)
    assert guided[1] == pytest.approx(2 * f_mean)


def test_both_rates_rising_in_free_motion_leave_ik_half_the_weight():
    # why raises_ik asks ẇ2 < 0 too: the eq. 29 logits saturate, so two rising rates end level
    logits = torch.tensor([0.0, -3.0, -3.0])
    for _ in range(400):  # 4 s at 100 Hz: a logit crosses its range of σw = 6 in 1/ẇ s (3.3 s at ẇ2 = 0.3)
        logits, w = integrate_weights(logits, torch.tensor([0.6, 0.3, -0.6]))
    assert float(w[0]) == pytest.approx(float(w[1]), abs=1e-6) and float(w[0]) < 0.51
    for _ in range(400):
        logits, w = integrate_weights(logits, torch.tensor([0.6, -0.3, -0.6]))
    assert float(w[0]) > 0.99


@pytest.mark.parametrize("free, guided, raises, yielding", [
    ([0.5, -0.5, 0.8, -1.0], [0.0, 0.4, 0.9, -0.3], True, True),     # FC rising with IK is allowed: it only damps
    ([0.5, 0.3, -0.6, -1.0], [0.0, 0.4, 0.9, -0.3], False, True),    # admittance rising with IK
    ([-0.1, -0.5, 0.8, -1.0], [0.0, 0.4, 0.9, -0.3], False, True),   # IK falling
    ([0.5, -0.5, 0.8, -1.0], [0.0, -0.1, 0.9, -0.3], True, False),   # resists the hand
    ([0.5, -0.5, 0.8, -1.0], [0.0, 0.4, 0.9, 0.2], True, False),     # pushes back with a growing f_d
])
def test_margin_is_positive_exactly_when_both_checks_pass(free, guided, raises, yielding):
    policy = _stub(free, guided)
    margin, f, g = transfer_margin(policy)
    assert raises_ik(f) is raises and yields(g) is yielding
    assert (margin > 0) == (raises and yielding)
    assert margin == pytest.approx(min(free[0], -free[1], guided[1], -guided[3]))


def _rows(path) -> list[dict[str, float]]:
    with open(path, newline="") as f:
        return [{k: float(v) for k, v in r.items()} for r in csv.DictReader(f)]


def test_select_policy_keeps_the_largest_margin_of_the_window_and_resumes_exactly(tmp_path):
    base = {"a2c": {"compile": False, "log_every": 1, "checkpoint_every": 3, "region_checks": 0, "learning_rate": 3e-2,
                    "select_policy": "transfer", "select_last": 0.5},
            "point_mass": {"episode_steps": 30}}
    cfg = config_from_dict(base)
    train(cfg, tmp_path / "run", total_steps=16 * 8)
    rows = _rows(tmp_path / "run" / "metrics.csv")
    assert [int(r["update"]) for r in rows] == list(range(1, 9))
    assert all(math.isfinite(r["transfer_margin"]) for r in rows)
    for r in rows:  # the margin is the minimum of its four terms
        assert r["transfer_margin"] == pytest.approx(min(r["free_w1"], -r["free_w2"], r["guided_w2"], -r["guided_fd"]))
    margins = [r["transfer_margin"] for r in rows]
    assert len(set(margins)) > 1  # the rates move while training, or there would be nothing to choose
    window = rows[4:]  # updates 5-8
    best = max(r["transfer_margin"] for r in window)
    chosen = max(int(r["update"]) for r in window if r["transfer_margin"] == best)  # a later row wins a tie
    saved = torch.load(tmp_path / "run" / "policy.pt", weights_only=True)
    assert saved["selected_update"] == chosen and saved["transfer_margin"] == pytest.approx(best)
    assert transfer_margin(load_policy(tmp_path / "run" / "policy.pt"))[0] == pytest.approx(best, abs=1e-6)
    # the last parameters are what a plain run of the same seed saves: training itself is unchanged
    plain = config_from_dict({**base, "a2c": {**base["a2c"], "select_policy": "last"}})
    train(plain, tmp_path / "plain", total_steps=16 * 8)
    ck = torch.load(tmp_path / "run" / "checkpoint.pt", weights_only=True)
    last = torch.load(tmp_path / "plain" / "policy.pt", weights_only=True)["flat"]
    assert torch.equal(ck["flat"], last)
    assert torch.equal(saved["flat"], last) == (chosen == 8)
    assert _rows(tmp_path / "plain" / "metrics.csv")[-1]["transfer_margin"] == pytest.approx(margins[-1])

    # killed after update 7 (last checkpoint: 6, inside the window), resumed: the same selection
    def kill(step, row):
        if step == 16 * 7:
            raise KeyboardInterrupt

    with pytest.raises(KeyboardInterrupt):
        train(cfg, tmp_path / "killed", total_steps=16 * 8, callback=kill)
    train(cfg, tmp_path / "killed", total_steps=16 * 8, resume=True)
    resumed = torch.load(tmp_path / "killed" / "policy.pt", weights_only=True)
    assert torch.equal(resumed["flat"], saved["flat"]) and resumed["selected_update"] == chosen

    # the plot: a panel per run, the kept update named; a run from before the columns is refused with its path
    from a3cqp_rl.cli import main
    from a3cqp_rl.plotting.transfer_history import kept_update

    assert kept_update(tmp_path / "run") == chosen and kept_update(tmp_path / "plain") is None
    assert main(["plot", "transfer", str(tmp_path / "run"), str(tmp_path / "plain"), "--out",
                 str(tmp_path / "t.png")]) == 0
    assert (tmp_path / "t.png").read_bytes()[:4] == b"\x89PNG"
    old = tmp_path / "old"
    old.mkdir()
    (old / "metrics.csv").write_text("step,update,policy_loss\n16,1,0.5\n")
    assert main(["plot", "transfer", str(old)]) == 2


def test_select_policy_config_is_checked():
    for a2c, msg in (({"select_last": 0.0}, "select_last"), ({"select_last": 1.5}, "select_last"),
                     ({"select_last": float("nan")}, "select_last"), ({"select_policy": "best"}, "select_policy"),
                     ({"select_policy": "transfer", "average_last": 0.2}, "set one of them")):
        with pytest.raises(ConfigError, match=msg):
            config_from_dict({"a2c": a2c})
    # a policy that is not the per-axis agents' (eq. 26 observation, four actions) cannot be checked
    layout = ParamLayout(5, 2, (8,), "separate", 5)
    spec = SimpleNamespace(low=None, high=None)
    with pytest.raises(ValueError, match="3 observations, 4 actions"):
        TransferSelection(layout, spec, 10, A2CConfig(select_policy="transfer"))
    assert TransferSelection(layout, spec, 10, A2CConfig())(5, torch.zeros(layout.size)) == {}


def test_train_says_which_parameters_it_kept():
    from algorithms.train import _selection_text

    kept = _selection_text(SimpleNamespace(selected_update=9500, updates=15625, transfer_margin=0.55,
                                           panda_selection=[]), 0.5)
    assert "after update 9,500 of 15,625" in kept and "(+0.55)" in kept and "last 50%" in kept
    assert "will probably not drive the Panda" not in kept
    none = _selection_text(SimpleNamespace(selected_update=15625, updates=15625, transfer_margin=-0.2,
                                           panda_selection=[]), 0.5)
    assert "(-0.20)" in none and "will probably not drive the Panda" in none
