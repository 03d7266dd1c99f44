"""`a3cqp evaluate --scene`: every controller on the same trials, Table VI metrics, JSON, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml

from a3cqp_rl.checkpoint import save_atomic
from a3cqp_rl.config import config_from_dict
from algorithms.networks import ParamLayout
from envs.panda_eval import PAPER_TABLE_VI, evaluate, format_table, main, to_json

FAST = {"panda": {"peg_in_hole": {"settle_time": 0.1, "approach_time": 1.0, "align_time": 2.0, "time_limit": 2.0,
                                  "operator_disengage": False, "return_time": 0.5}}}


def test_every_controller_runs_the_same_trials_and_the_json_has_table_vi_keys() -> None:
    # idle_force "free": both controllers then align alike before contact (with "damps" the equal blend's idle
    # share damps its alignment, so its misalignment at contact is no longer a fingerprint of the trial)
    cfg = config_from_dict({"panda": {**FAST["panda"], "idle_force": "free"}})
    res = evaluate("peg_in_hole", None, trials=1, seed=0, config=cfg, controllers=("ik_fc", "equal"), progress=False,
                   sim_threads=2)  # the arms in 2 MuJoCo models (ShardedPandaSim)
    s = res.summary
    # same trial for both: the same approach offset (the misalignment is measured at the first contact: close)
    mt = {c: np.array(res.per_trial[c]["misalign_translation"], dtype=float) for c in s}
    assert np.all(np.abs(mt["ik_fc"] - mt["equal"]) < 3e-3) and np.all(mt["ik_fc"] > 0)
    doc = to_json(res, primary="ik_fc")
    for key in ("trials", "successes", "success_rate", "insertion_time_mean_s", "insertion_time_std_s",
                "misalignment_rotation_mean_deg", "misalignment_translation_mean_mm", "baselines", "paper"):
        assert key in doc
    assert set(doc["baselines"]) == {"equal"} and doc["paper"] == PAPER_TABLE_VI
    json.dumps(doc)  # JSON-ready (NaN written as null)
    table = format_table(res)
    assert "8.21 ± 0.24" in table and "ik_fc" in table
    ep = res.episodes["ik_fc"]
    assert ep["weights"].shape[1:] == (6, 3) and len(ep["time"]) == len(ep["depth"]) > 100


@pytest.mark.slow
def test_scripted_force_control_inserts_the_peg() -> None:
    res = evaluate("peg_in_hole", None, trials=4, seed=1, controllers=("ik_fc",), progress=False)
    s = res.summary["ik_fc"]
    assert s["successes"] >= 3 and 0.0 < s["insertion_time_mean_s"] < 15.0


def test_main_reports_bad_input_in_one_line(tmp_path, capsys) -> None:  # noqa: ANN001
    assert main(["--scene", "peg_in_hole", "--policy", str(tmp_path / "nope.pt"), "--trials", "1"]) == 2
    err = capsys.readouterr().err
    assert "policy file not found" in err and "Traceback" not in err
    assert main(["--scene", "peg_in_hole", "--trials", "0"]) == 2
    assert main(["--scene", "peg_in_hole", "--trials", "1", "--threads", "0"]) == 2
    assert "--threads must be >= 1" in capsys.readouterr().err
    assert main(["--scene", "peg_in_hole", "--trials", "1", "--workers", "0"]) == 2
    assert "--workers must be >= 1" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["--scene", "kitchen"])


def test_main_takes_the_learned_policy_from_the_config(tmp_path, capsys) -> None:  # noqa: ANN001
    path = tmp_path / "pol" / "policy.pt"
    layout = ParamLayout(3, 4, (64, 64), "separate")
    save_atomic({"format": 1, "flat": layout.init(torch.Generator().manual_seed(0), 0.0),
                 "layout": [3, 4, [64, 64], "separate", 3]}, path)
    cfg = tmp_path / "peg.yaml"
    cfg.write_text(yaml.safe_dump({"env": "panda", "panda": {**FAST["panda"], "policy": str(path.parent)}}))
    out = tmp_path / "res.json"
    assert main(["--scene", "peg_in_hole", "--config", str(cfg), "--controllers", "learned", "--trials", "1",
                 "--quiet", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    assert doc["controller"] == "learned" and doc["trials"] == 1
    # a configured policy that is missing: one line naming panda.policy
    cfg.write_text(yaml.safe_dump({"env": "panda", "panda": {**FAST["panda"], "policy": str(tmp_path / "no.pt")}}))
    capsys.readouterr()
    assert main(["--scene", "peg_in_hole", "--config", str(cfg), "--controllers", "learned", "--trials", "1"]) == 2
    err = capsys.readouterr().err
    assert "panda.policy" in err and "no.pt" in err and "Traceback" not in err
