"""`a2c.select_policy: panda` (algorithms.panda_select): a run's candidates judged on the Panda's peg-in-hole."""

import json
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch
import yaml

from a3cqp_rl.config import A2CConfig, config_from_dict
from a3cqp_rl.exceptions import ConfigError
from algorithms.a2c import train
from algorithms.networks import ParamLayout
from algorithms.panda_select import SELECTION_FILE, format_selection, rank_key, select_on_panda
from algorithms.policy import fingerprint, load_policy
from envs.panda_eval import evaluate

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = ROOT / "policies" / "point_mass_fig5_fd_1e6_seed0.pt"


def _peg_config(tmp_path: Path, **peg) -> Path:
    """configs/panda_peg_in_hole.yaml with the peg scene's procedure changed by `peg`, written under tmp_path."""
    d = yaml.safe_load((ROOT / "configs" / "panda_peg_in_hole.yaml").read_text())
    d["panda"]["policy"] = str(SHIPPED)
    d["panda"]["peg_in_hole"].update(peg)
    path = tmp_path / "peg.yaml"
    path.write_text(yaml.safe_dump(d))
    return path


def _row(update: int, margin: float, successes: int, time: float, yields: bool = True) -> dict:
    return {"update": update, "transfer_margin": margin, "successes": successes, "insertions": 8,
            "capped_time_mean_s": time, "trials": 8, "yields": yields}


def test_rank_puts_pegs_first_then_yielding_then_time_then_margin():
    rows = [_row(1, 0.9, 6, 7.0), _row(2, -0.5, 8, 9.0), _row(3, 0.1, 8, 6.5), _row(4, 0.3, 8, 6.5),
            _row(5, 0.8, 8, 6.0, yields=False)]
    assert [r["update"] for r in sorted(rows, key=rank_key)] == [4, 3, 2, 5, 1]
    table = format_selection(rows, 3)
    assert table.splitlines()[4].startswith("*") and "8/8" in table and "6.50" in table
    assert table.splitlines()[5].split()[3] == "no"


def test_select_config_is_checked(tmp_path):
    for a2c, msg in (({"select_candidates": 0}, "select_candidates"), ({"select_trials": 0}, "select_trials"),
                     ({"select_seed": -1}, "select_seed"), ({"select_config": " "}, "select_config"),
                     ({"select_policy": "panda", "average_last": 0.2}, "set one of them")):
        with pytest.raises(ConfigError, match=msg):
            config_from_dict({"a2c": a2c})
    # refused before any training: no run folder is made
    missing = config_from_dict({"a2c": {"select_policy": "panda", "select_config": str(tmp_path / "nope.yaml")}})
    with pytest.raises(FileNotFoundError, match="nope.yaml"):
        train(missing, tmp_path / "run", total_steps=64)
    assert not (tmp_path / "run").exists()
    with pytest.raises(ValueError, match="run folder"):
        train(config_from_dict({"a2c": {"select_policy": "panda"}}), None, total_steps=64)


def test_the_panda_result_outranks_the_margin_and_a_rerun_reuses_it(tmp_path, monkeypatch):
    # two candidates: the shipped policy, which inserts, and one that hands every axis to force control with f_d
    # falling to 0, which cannot follow the reference; that one is handed the larger margin, the Panda's pegs decide
    shipped = torch.load(SHIPPED, weights_only=True)
    meta = {k: v for k, v in shipped.items() if k not in ("flat", "format", "averaged_updates")}
    layout = ParamLayout(*shipped["layout"])
    bad = shipped["flat"].clone()
    views = layout.views(bad)
    views["pi.out.w"].zero_()
    views["pi.out.b"].copy_(torch.tensor([-3.0, -3.0, 3.0, -3.0]))  # ẇ3 > 0 > ẇ1, ẇ2, ḟd at every observation
    cfg = _peg_config(tmp_path, time_limit=7.0, operator_disengage=False)
    hp = A2CConfig(select_policy="panda", select_trials=1, select_seed=3, select_config=str(cfg))
    lines: list[str] = []
    chosen, rows = select_on_panda([(0.5, 20, bad), (-0.2, 10, shipped["flat"])], meta, tmp_path, hp,
                                   log=lines.append)
    assert chosen == 1 and [r["update"] for r in rows] == [20, 10]
    assert rows[0]["successes"] == 0 and rows[0]["capped_time_mean_s"] == pytest.approx(7.0)
    assert rows[1]["successes"] == 1 and rows[1]["capped_time_mean_s"] < 7.0
    # two candidates, two processes (the default on this machine's cores); a line each as it ends
    assert sorted(line.split(":")[0] for line in lines) == ["candidate 1/2", "candidate 2/2"]
    assert any(line.startswith("candidate 2/2") and "1/1 pegs" in line for line in lines)
    # the candidate files are what `a3cqp evaluate --policy` runs: the same parameters, the same numbers
    files = sorted((tmp_path / "candidates").glob("update_*.pt"))
    assert [f.name for f in files] == ["update_000010.pt", "update_000020.pt"]
    assert fingerprint(load_policy(files[0])) == fingerprint(load_policy(SHIPPED)) == rows[1]["fingerprint"]
    from a3cqp_rl.config import load_config

    again = evaluate("peg_in_hole", files[0], 1, 3, config=load_config(cfg), controllers=("learned",),
                     progress=False).summary["learned"]
    assert again["successes"] == 1 and again["capped_time_mean_s"] == pytest.approx(rows[1]["capped_time_mean_s"])
    # a rerun in the folder (a run stopped while selecting) reads the rows back; other trials are run anew
    import envs.panda_eval

    calls = []
    monkeypatch.setattr(envs.panda_eval, "evaluate", lambda *a, **k: calls.append(a) or (_ for _ in ()).throw(
        RuntimeError("evaluated again")))
    lines.clear()
    assert select_on_panda([(0.5, 20, bad), (-0.2, 10, shipped["flat"])], meta, tmp_path, hp,
                           log=lines.append) == (chosen, rows)
    assert not calls and all("(measured before)" in line for line in lines)
    with pytest.raises(RuntimeError, match="evaluated again"):
        select_on_panda([(0.5, 20, bad)], meta, tmp_path, A2CConfig(select_policy="panda", select_trials=1,
                                                                    select_seed=4, select_config=str(cfg)))
    saved = json.loads((tmp_path / "candidates" / SELECTION_FILE).read_text())["candidates"]
    assert {r["seed"] for r in saved} == {3}  # the interrupted seed-4 selection left no row


def test_train_writes_the_chosen_candidate_to_policy_pt(tmp_path):
    cfg_path = _peg_config(tmp_path, settle_time=0.1, approach_time=1.0, align_time=2.0, time_limit=2.0,
                           operator_disengage=False)
    cfg = config_from_dict({"a2c": {"compile": False, "log_every": 1, "checkpoint_every": 3, "region_checks": 0,
                                    "learning_rate": 3e-2, "select_policy": "panda", "select_candidates": 2,
                                    "select_trials": 1, "select_config": str(cfg_path)},
                            "point_mass": {"episode_steps": 30}})
    res = train(cfg, tmp_path / "run", total_steps=16 * 8)
    rows = res.panda_selection
    assert len(rows) == 2 and all(r["update"] >= 5 for r in rows)  # the run's second half: updates 5-8
    assert rows[0]["transfer_margin"] >= rows[1]["transfer_margin"]
    best = min(rows, key=rank_key)
    saved = torch.load(tmp_path / "run" / "policy.pt", weights_only=True)
    assert saved["selected_update"] == best["update"] == res.selected_update
    assert saved["panda_selection"]["successes"] == best["successes"]
    cand = torch.load(tmp_path / "run" / "candidates" / f"update_{best['update']:06d}.pt", weights_only=True)
    assert torch.equal(saved["flat"], cand["flat"])
    from algorithms.train import _selection_text

    text = _selection_text(res, 0.5)
    assert f"after update {best['update']:,} of 8" in text and "a2c.select_policy: panda" in text
    assert ("will probably miss pegs" in text) == (best["successes"] < best["insertions"])
    assert _selection_text(SimpleNamespace(selected_update=5, updates=8, transfer_margin=0.1, panda_selection=[]),
                           0.5).startswith("policy.pt: the parameters after update 5 of 8, the largest transfer")


def test_the_window_keeps_the_largest_margins_and_a_checkpoint_restores_them(monkeypatch):
    import algorithms.a2c_run as run

    margins = iter([0.3, -0.1, 0.5, 0.3, 0.2, 0.9])
    monkeypatch.setattr(run, "transfer_margin", lambda policy: (next(margins), [0.0] * 4, [0.0] * 4))
    layout = ParamLayout(3, 4, (4,), "separate", 3)
    spec = SimpleNamespace(low=None, high=None)
    sel = run.TransferSelection(layout, spec, 10, A2CConfig(select_policy="panda", select_candidates=3,
                                                            select_last=0.6))
    assert sel.first == 5
    for update in range(4, 10):  # update 4 is before the window: its margin 0.3 is not kept
        sel(update, torch.full((layout.size,), float(update)))
    assert [(m, u) for m, u, _ in sel.candidates] == [(0.9, 9), (0.5, 6), (0.3, 7)]  # a later row wins a tie
    assert sel.update == 9 and float(sel.best[0]) == 9.0
    sel.choose(2, {"successes": 8})
    assert sel.meta() == {"selected_update": 7, "transfer_margin": 0.3, "panda_selection": {"successes": 8}}
    back = run.TransferSelection(layout, spec, 10, A2CConfig(select_policy="panda", select_candidates=3,
                                                             select_last=0.6))
    back.load_state_dict(sel.state_dict(), 9)
    assert [(m, u) for m, u, _ in back.candidates] == [(0.9, 9), (0.5, 6), (0.3, 7)]
    # a checkpoint from before candidates were kept holds the best row alone
    old = run.TransferSelection(layout, spec, 10, A2CConfig(select_policy="transfer", select_last=0.6))
    old.load_state_dict({"first": 5, "best": torch.ones(layout.size), "update": 6, "margin": 0.5}, 8)
    assert old.update == 6 and old.margin == 0.5 and torch.equal(old.best, torch.ones(layout.size))
