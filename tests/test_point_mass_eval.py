"""envs.point_mass_eval and `a3cqp evaluate`: metrics on scripted policies with known behaviour, same episodes for
every policy, checks, JSON and the CLI."""

import json

import pytest
import torch

from a3cqp_rl.config import config_from_dict
from envs.evaluate_cli import PANDA_CHECK, PANDA_HINT
from envs.point_mass import PointMassEnv, agent_step
from envs.point_mass_eval import (EVAL_SCENARIOS, baseline_policies, behaviour_checks, evaluate, scenario_config,
                                  switching_rule)

E = 16


@pytest.fixture(scope="module")
def baselines():
    return evaluate(baseline_policies(), episodes=E, seed=3)


def test_admittance_yields_and_ik_does_not(baselines):
    m = baselines.metrics
    adm, ik = m["admittance_only"]["operator"]["f_ope_active"], m["ik_only"]["operator"]["f_ope_active"]
    assert adm < 0.3 * ik and ik > 8.0, (adm, ik)
    assert m["admittance_only"]["guided_contact"]["f_ope_active"] < 0.3 * m["ik_only"]["guided_contact"]["f_ope_active"]
    # after letting go, IK returns to its target; admittance stays where the hand left it
    assert m["ik_only"]["operator"]["final_e"] < 0.002 < 0.02 < m["admittance_only"]["operator"]["final_e"]


def test_ik_reaches_free_targets_and_admittance_does_not(baselines):
    ik, adm = baselines.metrics["ik_only"]["free"], baselines.metrics["admittance_only"]["free"]
    assert ik["reached"] == 1.0 and ik["final_e"] < 1e-3 and 0.1 < ik["time_to_2cm"] < 1.0
    assert adm["reached"] < 0.5 and adm["final_e"] > 0.1
    assert baselines.metrics["force_control"]["free"]["reached"] == 0.0  # f_d = 20 N with nothing to push on


def test_force_control_holds_a_bounded_force_on_the_wall(baselines):
    fc = baselines.metrics["force_control"]["contact"]
    f_d_max = config_from_dict({}).adaptation.f_d_max
    assert fc["force_mean"] == pytest.approx(f_d_max, abs=0.3) and fc["force_peak"] < f_d_max + 0.5
    assert fc["in_band"] == 1.0
    assert baselines.metrics["admittance_only"]["contact"]["in_band"] == 0.0  # never presses


def test_every_policy_sees_the_same_episodes_and_the_seed_decides_them():
    rule = switching_rule()
    a = evaluate({"one": rule, "two": rule}, episodes=8, seed=1, scenarios=["free", "operator"])
    assert a.metrics["one"] == a.metrics["two"]
    assert evaluate({"one": rule}, episodes=8, seed=1, scenarios=["free", "operator"]).metrics["one"] == a.metrics["one"]
    assert evaluate({"one": rule}, episodes=8, seed=2, scenarios=["free"]).metrics["one"] != a.metrics["one"]["free"]


def test_checks_and_json(baselines, tmp_path):
    c = behaviour_checks(baselines, "switching_rule", literal_regions=4)
    assert c["regions"] and c["reaches"] and c["bounded"]
    assert not behaviour_checks(baselines, "admittance_only")["reaches"]
    assert behaviour_checks(baselines, "admittance_only")["yields"]
    assert not behaviour_checks(baselines, "ik_only")["yields"]
    best = max(baselines.policies, key=baselines.return_mean)
    assert behaviour_checks(baselines, best)["best_return"]
    path = baselines.write_json(tmp_path / "e.json", {"note": 1})
    data = json.loads(path.read_text())
    assert data["episodes"] == E and data["note"] == 1
    assert data["policies"]["admittance_only"]["free"]["time_to_2cm"] is None  # NaN: never within 2 cm
    assert data["policies"]["ik_only"]["return_mean"] == pytest.approx(baselines.return_mean("ik_only"))
    text = baselines.table()
    assert text.count("| switching_rule |") == 2 and "mean return" in text


def test_bad_policies_and_arguments():
    with pytest.raises(ValueError, match="shape"):
        evaluate({"bad": lambda o: o}, episodes=2, scenarios=["free"])
    with pytest.raises(ValueError, match="NaN"):
        evaluate({"bad": lambda o: torch.full((o.shape[0], 4), float("nan"))}, episodes=2, scenarios=["free"])
    with pytest.raises(ValueError, match="unknown scenario"):
        evaluate(baseline_policies(), episodes=2, scenarios=["moon"])
    with pytest.raises(ValueError, match="episodes"):
        evaluate(baseline_policies(), episodes=0)


def test_hand_operator_follows_a_minimum_jerk_path_through_a_bounded_grip():
    """With IK holding the mass the grip force saturates at f̄_ope; a floating mass follows the hand to its goal."""
    cfg = scenario_config(config_from_dict({}), EVAL_SCENARIOS["operator"])
    env = PointMassEnv(32, cfg, seed=0)
    env.reset()
    state, sched = env.functional()
    holding = sched[0, :, :-1] != 0
    for rates, name in (((1.0, -1.0, -1.0, -1.0), "ik"), ((-1.0, -1.0, 1.0, -1.0), "float")):
        s = {k: v.clone() for k, v in state.items()}
        s["w_logits"] = 3.0 * torch.tensor(rates[:3], dtype=torch.float64).expand(32, 3).clone()
        s["f_d"].zero_()
        f = []
        for t in range(cfg.point_mass.episode_steps):
            s, _ = agent_step(s, torch.tensor(rates, dtype=torch.float64).expand(32, 4), sched, cfg.point_mass,
                              cfg.adaptation, cfg.reward)
            f.append(s["f_ope"])
        f = torch.stack(f, 1)
        assert f.abs().max() <= cfg.adaptation.f_ope_max + 1e-9 and bool((f[~holding] == 0).all())
        if name == "ik":
            assert f.abs().max() > cfg.adaptation.f_ope_max - 1e-6
        else:  # the hand ends its move at a displacement of 10-30 cm
            assert 0.05 < s["x"].abs().max() < 0.7


def test_evaluate_cli(tmp_path, capsys):
    from a3cqp_rl.cli import main
    from algorithms.a2c import train

    for run in ("a", "b"):
        train(config_from_dict({"a2c": {"compile": False, "log_every": 10, "region_checks": 0}}), tmp_path / run,
              total_steps=160)
    out = tmp_path / "eval.json"
    assert main(["evaluate", "--policy", str(tmp_path / "a"), str(tmp_path / "b" / "policy.pt"), "--episodes", "2",
                 "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| a |" in printed and "| b |" in printed and "| admittance_only |" in printed and "best_return" in printed
    data = json.loads(out.read_text())
    assert set(data["checks"]) == {"a", "b"} and "guided_contact" in data["policies"]["a"]
    # the Panda's free-motion check, per policy (its sign decides the words)
    rates, rates2 = data["free_motion_w1_rate"], data["free_motion_w2_rate"]
    assert set(rates) == set(rates2) == {"a", "b"}
    raises = {n: r > 0 > rates2[n] for n, r in rates.items()}  # IK over admittance
    def said(word, *rates):  # noqa: ANN001, ANN202 (rates within ±0.05 are called flat: a sign says little there)
        return f"{word}, but flat: |rates| < 0.05" if max(map(abs, rates)) < 0.05 else word

    for n, r in rates.items():
        word = said("raises IK" if raises[n] else "does not raise IK", r, rates2[n])
        assert f"{n} ẇ1 {r:+.2f} ẇ2 {rates2[n]:+.2f} ({word})" in printed
    for n, (a, d) in data["guided_w2_fd_rates"].items():
        assert f"{n} ẇ2 {a:+.2f} ḟd {d:+.2f} ({said('yields' if a > 0 and d < 0 else 'resists', a, d)})" in printed
    assert any(max(abs(r), abs(rates2[n])) < 0.05 for n, r in rates.items())  # these short runs are flat
    failing = not all(raises.values()) or any(not (a > 0 and d < 0) for a, d in data["guided_w2_fd_rates"].values())
    assert (PANDA_HINT in printed) == failing  # the way to a policy that transfers, only where one does not
    passing = [n for n in rates if raises[n] and (lambda a, d: a > 0 and d < 0)(*data["guided_w2_fd_rates"][n])]
    check = [line for line in printed.splitlines() if line.startswith(PANDA_CHECK)]
    assert check == ([f"{PANDA_CHECK} --policy " + " ".join(str(tmp_path / n) for n in passing)] if passing else [])
    assert main(["evaluate", "--episodes", "2"]) == 0  # baselines only
    assert main(["evaluate", "--policy", str(tmp_path / "missing.pt")]) == 2
    assert "not found" in capsys.readouterr().err



def test_evaluate_cli_hands_panda_scenes_to_panda_eval(monkeypatch, capsys):
    import sys
    import types

    from a3cqp_rl.cli import main

    seen = []
    monkeypatch.setitem(sys.modules, "envs.panda_eval", types.SimpleNamespace(main=lambda argv: seen.append(argv) or 7))
    assert main(["evaluate", "--scene", "polishing", "--episodes", "3"]) == 7
    assert seen == [["--scene", "polishing", "--episodes", "3"]]
    monkeypatch.setitem(sys.modules, "envs.panda_eval", None)  # a version without the Panda scenes
    assert main(["evaluate", "--scene=peg_in_hole"]) == 2
    assert "Panda scenes are not available" in capsys.readouterr().err


def test_policies_that_pass_both_panda_rules_are_named_with_the_command_that_checks_them(capsys):
    from pathlib import Path

    from envs.evaluate_cli import report

    shipped = Path(__file__).parents[1] / "policies" / "point_mass_fig5_fd_1e6_seed0.pt"  # raises IK and yields
    report([shipped], episodes=2)
    printed = capsys.readouterr().out
    assert f"{PANDA_CHECK} --policy {shipped}" in printed.splitlines()
    assert PANDA_HINT not in printed


def test_more_episodes_than_the_memory_holds_are_refused_before_allocating(capsys):
    from a3cqp_rl.cli import main
    from a3cqp_rl.exceptions import ConfigError

    with pytest.raises(ConfigError, match="100,000,000 episodes per scenario for 5 policies need about .* GiB"):
        evaluate(baseline_policies(), episodes=100_000_000)
    assert main(["evaluate", "--episodes", "100000000"]) == 2
    err = capsys.readouterr().err
    assert "use fewer episodes" in err and "Traceback" not in err
