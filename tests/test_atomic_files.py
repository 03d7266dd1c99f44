"""Text and JSON outputs are written atomically: a temp file beside the target, renamed over it."""
from __future__ import annotations

import csv
import json
import math
import stat

import pytest

from a3cqp_rl.checkpoint import write_atomic, write_text_atomic


def test_write_text_atomic_creates_folders_leaves_no_temp_and_is_readable(tmp_path) -> None:
    path = write_text_atomic(tmp_path / "a" / "b" / "out.json", '{"x": 1}\n')
    assert path.read_text() == '{"x": 1}\n'
    assert sorted(p.name for p in path.parent.iterdir()) == ["out.json"]
    assert stat.S_IMODE(path.stat().st_mode) == 0o644


def test_write_text_atomic_keeps_the_old_file_when_the_write_fails(tmp_path) -> None:
    path = write_text_atomic(tmp_path / "out.txt", "old\n")

    def fails(f):  # noqa: ANN001, ANN202
        f.write(b"half")
        raise RuntimeError("disk gone")

    with pytest.raises(RuntimeError):
        write_atomic(path, fails)
    assert path.read_text() == "old\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_a_failed_write_names_the_file_asked_for_not_the_temporary_one(tmp_path) -> None:
    def full(f):  # noqa: ANN001, ANN202
        raise OSError(28, "No space left on device", f.name)

    with pytest.raises(OSError) as exc:
        write_atomic(tmp_path / "r.json", full)
    assert exc.value.filename == str(tmp_path / "r.json") and exc.value.errno == 28
    assert ".tmp" not in str(exc.value) and "No space left" in str(exc.value)
    assert list(tmp_path.iterdir()) == []


def test_panda_and_point_mass_json_writers_go_through_it(tmp_path, monkeypatch) -> None:
    import a3cqp_rl.checkpoint as checkpoint
    import envs.panda_eval as panda_eval
    import envs.point_mass_eval as point_mass_eval

    seen = []
    real = checkpoint.write_text_atomic

    def spy(path, text):  # noqa: ANN001, ANN202
        seen.append(path)
        return real(path, text)

    monkeypatch.setattr(panda_eval, "write_text_atomic", spy)
    panda_eval._write_json(tmp_path / "p" / "results.json", {"trials": 2})
    assert json.loads((tmp_path / "p" / "results.json").read_text()) == {"trials": 2}
    monkeypatch.setattr(checkpoint, "write_text_atomic", spy)  # under write_output_text ("-": standard output)
    res = point_mass_eval.EvalResult.__new__(point_mass_eval.EvalResult)
    monkeypatch.setattr(point_mass_eval.EvalResult, "to_dict", lambda self: {"v": math.nan})
    res.write_json(tmp_path / "m.json")
    assert json.loads((tmp_path / "m.json").read_text()) == {"v": None}
    assert [p.name for p in seen] == ["results.json", "m.json"]


def test_the_recorded_episodes_are_written_atomically(tmp_path, monkeypatch) -> None:
    import numpy as np

    import envs.panda_eval as panda_eval

    panda_eval.write_episodes(tmp_path, {"learned": {"t": np.arange(3.0)}, "ik": {"t": np.zeros(2)}})
    with np.load(tmp_path / "episode_learned.npz") as z:
        assert z["t"].tolist() == [0.0, 1.0, 2.0]

    def fails(f, **arrays):  # noqa: ANN001, ANN003, ANN202
        f.write(b"PK half a zip")
        raise OSError("disk full")

    monkeypatch.setattr(np, "savez_compressed", fails)
    with pytest.raises(OSError):
        panda_eval.write_episodes(tmp_path, {"learned": {"t": np.ones(4)}})
    monkeypatch.undo()
    with np.load(tmp_path / "episode_learned.npz") as z:  # the previous file, whole
        assert z["t"].tolist() == [0.0, 1.0, 2.0]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode_ik.npz", "episode_learned.npz"]


def test_a_resumed_runs_metrics_file_is_rewritten_atomically(tmp_path, monkeypatch) -> None:
    import algorithms.run_log as run_log

    path = tmp_path / "metrics.csv"
    path.write_text("update,step,policy_loss\n1,16,0.5\n2,32,0.4\n3,48,0.3\n")
    before = path.read_text()

    def fails(p, text):  # noqa: ANN001, ANN202
        raise OSError("killed while writing")

    monkeypatch.setattr(run_log, "write_text_atomic", fails)
    with pytest.raises(OSError):
        run_log.truncate_csv(path, keep_until_update=2, log_every=1)
    assert path.read_text() == before  # nothing was written in place
    monkeypatch.undo()
    run_log.truncate_csv(path, keep_until_update=2, log_every=1)
    rows = list(csv.DictReader(path.open(newline="")))
    assert [r["update"] for r in rows] == ["1", "2"] and [r["policy_loss"] for r in rows] == ["0.5", "0.4"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["metrics.csv"]


def test_a_run_folder_written_again_keeps_no_episode_of_the_earlier_run(tmp_path) -> None:
    import numpy as np

    import envs.panda_eval as panda_eval

    panda_eval.write_episodes(tmp_path, {"ik": {"t": np.zeros(2)}, "ik_fc": {"t": np.zeros(2)},
                                         "equal": {"t": np.zeros(2)}})
    for name in ("episode_equal.png", "episode_equal_strip.png", "episode_ik.png", "notes.txt"):
        (tmp_path / name).write_text("")
    assert panda_eval.write_episodes(tmp_path, {"ik_fc": {"t": np.ones(3)}}) == ["equal", "ik"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["episode_ik_fc.npz", "notes.txt"]
