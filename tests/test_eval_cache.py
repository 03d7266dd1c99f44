"""`a3cqp evaluate --scene ... --cache DIR`: each seed's result kept as it ends and read back by the same command."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from a3cqp_rl.config import config_from_dict
from envs import eval_cache, panda_eval
from envs.panda_eval import evaluate_seeds, main

ROOT = Path(__file__).resolve().parents[1]
FAST = {"panda": {"peg_in_hole": {"settle_time": 0.1, "approach_time": 1.0, "align_time": 2.0, "time_limit": 2.0,
                                  "operator_disengage": False, "return_time": 0.5}}}


def test_a_rerun_reads_every_finished_seed_back_and_other_settings_measure_anew(tmp_path, monkeypatch) -> None:
    cfg = config_from_dict(FAST)
    kw = dict(config=cfg, controllers=("ik_fc",), progress=False)
    said: list[str] = []
    first = evaluate_seeds("peg_in_hole", None, 1, [0, 1], cache=tmp_path, log=said.append, **kw)
    files = sorted(p.name for p in tmp_path.iterdir())
    assert len(files) == 2 and files[0].startswith("seed_0_") and files[1].startswith("seed_1_") and not said
    calls = []
    real = panda_eval.evaluate

    def counting(*a, **k):  # noqa: ANN002, ANN003, ANN202
        calls.append(a[3])
        return real(*a, **k)

    monkeypatch.setattr(panda_eval, "evaluate", counting)
    again = evaluate_seeds("peg_in_hole", None, 1, [0, 1, 2], cache=tmp_path, log=said.append, **kw)
    assert calls == [2] and len(said) == 2 and "seed 0: read back" in said[0]  # only the new seed is simulated
    for k, v in first.per_trial["ik_fc"].items():
        assert again.per_trial["ik_fc"][k][:2] == v, k
    assert again.summary["ik_fc"]["trials"] == 3 and again.seeds == (0, 1, 2)
    ep, ep0 = again.episodes["ik_fc"], first.episodes["ik_fc"]
    assert ep.keys() == ep0.keys() and isinstance(ep["scene"], str)
    assert all(np.array_equal(ep[k], ep0[k]) for k in ep if not isinstance(ep[k], str))
    # another setting (here the time limit) is another key: measured anew, the old files kept
    calls.clear()
    other = config_from_dict({"panda": {"peg_in_hole": {**FAST["panda"]["peg_in_hole"], "time_limit": 2.5}}})
    evaluate_seeds("peg_in_hole", None, 1, [0], cache=tmp_path, **{**kw, "config": other})
    assert calls == [0] and len(list(tmp_path.glob("seed_0_*.npz"))) == 2


def test_an_unreadable_or_foreign_file_is_measured_again(tmp_path, caplog) -> None:  # noqa: ANN001
    cfg = config_from_dict(FAST)
    kw = dict(config=cfg, controllers=("ik_fc",), progress=False)
    key = eval_cache.result_key("peg_in_hole", None, 1, 0, cfg, controllers=("ik_fc",), progress=False)
    path = eval_cache.key_file(tmp_path, key)
    path.write_bytes(b"not an npz")
    res = evaluate_seeds("peg_in_hole", None, 1, [0], cache=tmp_path, **kw)
    assert "cannot be read" in caplog.text and res.summary["ik_fc"]["trials"] == 1
    assert eval_cache.load(path, key, 0) is not None  # rewritten
    foreign = {**key, "trials": 2}
    assert eval_cache.load(path, foreign, 0) is None  # a file holds its own key: another key never reads it
    whole = path.read_bytes()
    for broken in (whole[: len(whole) // 2], b""):  # cut short (not a zip), empty (no data): warned, not raised
        caplog.clear()
        path.write_bytes(broken)
        assert eval_cache.load(path, key, 0) is None and "cannot be read" in caplog.text


def test_the_key_follows_the_policy_s_parameters_and_the_code() -> None:
    cfg = config_from_dict(FAST)
    a = eval_cache.result_key("peg_in_hole", "aaaa", 26, 0, cfg, controllers=("learned",), workers=2)
    b = eval_cache.result_key("peg_in_hole", "bbbb", 26, 0, cfg, controllers=("learned",), workers=2)
    assert eval_cache.key_file(eval_cache.Path("."), a) != eval_cache.key_file(eval_cache.Path("."), b)
    assert a["code"] == eval_cache.code_digest() and len(a["code"]) == 16
    json.dumps(a)  # JSON-ready
    # the learned controller's policy defaults to the config's panda.policy: its parameters are in the key
    shipped = config_from_dict({"panda": {"policy": str(ROOT / "policies" / "point_mass_fig5_fd_1e6_seed0.pt")}})
    assert eval_cache._fingerprint(None, {"config": shipped, "controllers": ("learned", "ik")}) == "1e07d20ac2d5224d"
    assert eval_cache._fingerprint(None, {"config": shipped, "controllers": ("ik",)}) is None


def test_main_resumes_a_sweep_with_cache(tmp_path, capsys, monkeypatch) -> None:  # noqa: ANN001
    cfg_path = tmp_path / "fast.yaml"
    import yaml

    cfg_path.write_text(yaml.safe_dump(FAST))
    args = ["--scene", "peg_in_hole", "--trials", "1", "--seeds", "0-1", "--controllers", "ik_fc", "--config",
            str(cfg_path), "--workers", "1", "--quiet", "--cache", str(tmp_path / "c"), "--json", str(tmp_path / "r.json")]
    assert main(args) == 0
    first = json.loads((tmp_path / "r.json").read_text())
    assert first["read_back_seeds"] == [] and "read back" not in capsys.readouterr().out
    monkeypatch.setattr(panda_eval, "evaluate", lambda *a, **k: pytest.fail("simulated again"))
    assert main(args) == 0
    captured = capsys.readouterr()
    assert captured.err.count("read back from") == 2
    # the header says its wall time is the one measured when the seeds were simulated, not this run's
    assert f"every seed read back from {tmp_path / 'c'}, the wall time as measured then" in captured.out
    again = json.loads((tmp_path / "r.json").read_text())
    assert again["per_trial"] == first["per_trial"] and again["seeds"] == [0, 1]
    assert again["read_back_seeds"] == [0, 1] and again["wall_seconds"] == first["wall_seconds"]


def test_a_result_that_needs_pickle_is_not_kept(tmp_path, caplog) -> None:  # noqa: ANN001
    from envs.panda_report import EvalResult

    ragged = np.empty(2, dtype=object)
    ragged[:] = [np.zeros(1), np.zeros(2)]
    res = EvalResult(scene="peg_in_hole", summary={}, per_trial={}, episodes={"ik": {"q": ragged}}, seconds=1.0,
                     sim_seconds=2.0, metrics={"ik": {"success": np.array([True, False])}}, seeds=(0,))
    eval_cache.save(tmp_path / "x.npz", {"seed": 0}, res)
    assert not (tmp_path / "x.npz").exists() and "not written" in caplog.text and "e|ik|q" in caplog.text


def test_main_says_what_an_interrupted_sweep_kept(tmp_path, capsys, monkeypatch) -> None:  # noqa: ANN001
    """Ctrl-C during the second seed: exit 130 with one line (no traceback), the first seed kept for the rerun."""
    cfg_path = tmp_path / "fast.yaml"
    import yaml

    cfg_path.write_text(yaml.safe_dump(FAST))
    real, calls = panda_eval.evaluate, []

    def interrupted_second(*a, **k):  # noqa: ANN002, ANN003, ANN202
        calls.append(1)
        if len(calls) == 2:
            raise KeyboardInterrupt
        return real(*a, **k)

    monkeypatch.setattr(panda_eval, "evaluate", interrupted_second)
    args = ["--scene", "peg_in_hole", "--trials", "1", "--seeds", "0-1", "--controllers", "ik_fc", "--config",
            str(cfg_path), "--workers", "1", "--quiet", "--cache", str(tmp_path / "c")]
    assert main(args) == 130
    err = capsys.readouterr().err
    assert "interrupted; the seeds that ended are kept in" in err and "Traceback" not in err
    monkeypatch.setattr(panda_eval, "evaluate", real)
    assert main(args) == 0
    captured = capsys.readouterr()
    assert captured.err.count("read back from") == 1  # seed 0 from the cache, seed 1 simulated
    assert "; 1 of 2 seeds read back from" in captured.out
