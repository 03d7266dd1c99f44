"""Run folders: no silent overwrite, one writer, no silent relabelling, exact resumes, Ctrl-C keeps the work."""

import csv
import os
import signal
from pathlib import Path

import pytest
import torch

from a3cqp_rl.cli import main
from a3cqp_rl.config import config_from_dict
from a3cqp_rl.exceptions import CheckpointError
from a3cqp_rl.run_folder import RunFolder, RunFolderError, config_changes
from algorithms.a2c import train

BASE = {"a2c": {"compile": False, "log_every": 5, "checkpoint_every": 10, "region_checks": 0},
        "point_mass": {"episode_steps": 30}}
CONFIG = str(Path(__file__).parents[1] / "configs" / "point_mass_a2c.yaml")


def _flat(run):
    return torch.load(run / "policy.pt", weights_only=True)["flat"]


def _rows(run):
    with (run / "metrics.csv").open() as f:
        return [{k: v for k, v in r.items() if k != "steps_per_second"} for r in csv.DictReader(f)]


def test_a_finished_run_is_not_overwritten_without_force(tmp_path):
    cfg = config_from_dict(BASE)
    train(cfg, tmp_path / "run", total_steps=16 * 20)
    before = (tmp_path / "run" / "metrics.csv").read_text()
    with pytest.raises(RunFolderError, match="already holds a run.*--resume.*--force"):
        train(cfg, tmp_path / "run", total_steps=16 * 10)
    assert (tmp_path / "run" / "metrics.csv").read_text() == before
    (tmp_path / "run" / "notes.txt").write_text("mine")
    for old in ("evaluation.json", "transfer.png", "policy_map.png"):  # what train writes after training
        (tmp_path / "run" / old).write_text("the old run's")
    train(cfg, tmp_path / "run", total_steps=16 * 10, force=True)  # starts over: 10 updates, 2 rows
    assert len(_rows(tmp_path / "run")) == 2 and (tmp_path / "run" / "notes.txt").read_text() == "mine"
    assert not any((tmp_path / "run" / old).exists() for old in ("evaluation.json", "transfer.png", "policy_map.png"))
    # a run without its checkpoint is not sent to --resume (which would say there is nothing to resume)
    (tmp_path / "run" / "checkpoint.pt").unlink()
    with pytest.raises(RunFolderError, match="without checkpoint.pt it cannot be resumed: start over with --force"):
        train(cfg, tmp_path / "run", total_steps=16 * 10)


def test_a_folder_with_only_a_checkpoint_names_the_file_to_pass_as_a_policy(tmp_path):
    from a3cqp_rl.exceptions import CheckpointError
    from a3cqp_rl.run_folder import policy_file
    from algorithms.policy import load_policy

    train(config_from_dict(BASE), tmp_path / "run", total_steps=16 * 2)
    assert policy_file(tmp_path / "run") == tmp_path / "run" / "policy.pt"
    assert policy_file(tmp_path / "run" / "checkpoint.pt") == tmp_path / "run" / "checkpoint.pt"
    (tmp_path / "run" / "policy.pt").unlink()
    with pytest.raises(CheckpointError, match=r"holds no policy.pt .* pass .*run/checkpoint.pt for its last parameters"):
        load_policy(tmp_path / "run")
    assert load_policy(tmp_path / "run" / "checkpoint.pt").layout.obs_dim == 3
    assert policy_file(tmp_path / "empty") == tmp_path / "empty"  # not a folder: the loader says it is not found


def test_one_writer_per_folder(tmp_path):
    with RunFolder.open(tmp_path / "run"):
        with pytest.raises(RunFolderError, match=f"being written by another process \\(pid {os.getpid()}\\)"):
            train(config_from_dict(BASE), tmp_path / "run", total_steps=16)
        # a resume of a run that has no checkpoint yet says so too, not "nothing to resume"
        with pytest.raises(RunFolderError, match="being written by another process"):
            train(config_from_dict(BASE), tmp_path / "run", total_steps=16, resume=True)
    with pytest.raises(CheckpointError, match="nothing to resume"):
        train(config_from_dict(BASE), tmp_path / "run", total_steps=16, resume=True)
    train(config_from_dict(BASE), tmp_path / "run", total_steps=16)  # released


def test_resume_refuses_a_changed_config_unless_overridden_and_records_it(tmp_path):
    cfg = config_from_dict(BASE)
    train(cfg, tmp_path / "run", total_steps=16 * 10)
    config_before = (tmp_path / "run" / "config.yaml").read_text()
    for change, text in (({"seed": 1}, "seed: 0 -> 1"), ({"a2c": {"learning_rate": 1e-3}}, "a2c.learning_rate")):
        other = config_from_dict({**BASE, **change, "a2c": {**BASE["a2c"], **change.get("a2c", {})}})
        with pytest.raises(CheckpointError, match=text):
            train(other, tmp_path / "run", total_steps=16 * 20, resume=True)
    # another network: refused whatever --override says, with what of the config differs
    other = config_from_dict({**BASE, "a2c": {**BASE["a2c"], "hidden": [8]}})
    with pytest.raises(CheckpointError, match=r"written for network .*the config differs from the run's \(a2c.hidden"):
        train(other, tmp_path / "run", total_steps=16 * 20, resume=True, override=True)
    assert not (tmp_path / "run" / "overrides.log").exists()
    assert (tmp_path / "run" / "config.yaml").read_text() == config_before  # a refused resume relabels nothing
    # more steps and --no-compile are no change of the experiment
    train(config_from_dict({**BASE, "a2c": {**BASE["a2c"], "total_steps": 5}}), tmp_path / "run", total_steps=16 * 12,
          resume=True)
    other = config_from_dict({**BASE, "a2c": {**BASE["a2c"], "learning_rate": 1e-3}})
    train(other, tmp_path / "run", total_steps=16 * 20, resume=True, override=True)
    log = (tmp_path / "run" / "overrides.log").read_text()
    assert "resume at update 12: a2c.learning_rate: 4.25339846e-06 -> 0.001" in log
    assert "learning_rate: 0.001" in (tmp_path / "run" / "config.yaml").read_text()
    assert config_changes({"a": {"b": 1, "c": 2}}, {"a": {"b": 1, "c": 3}}) == ["a.c: 2 -> 3"]


def test_episodes_are_counted_exactly_across_a_resume(tmp_path):
    base = {"a2c": {"compile": False, "log_every": 50, "checkpoint_every": 350, "region_checks": 0},
            "point_mass": {"episode_steps": 4}}
    cfg = config_from_dict(base)
    train(cfg, tmp_path / "full", total_steps=16 * 400)  # 4 envs x 1 episode per update: 1600 episodes
    train(cfg, tmp_path / "part", total_steps=16 * 350)  # the checkpoint keeps only the last 1000 returns
    train(cfg, tmp_path / "part", total_steps=16 * 400, resume=True)
    assert _rows(tmp_path / "full")[-1]["episodes"] == "1600"
    assert _rows(tmp_path / "part") == _rows(tmp_path / "full")


def test_resume_cleans_temporary_files_of_a_killed_writer(tmp_path):
    train(config_from_dict(BASE), tmp_path / "run", total_steps=16 * 10)
    orphan = tmp_path / "run" / ".checkpoint.pt.k3j4.tmp"
    orphan.write_bytes(b"half a checkpoint")
    train(config_from_dict(BASE), tmp_path / "run", total_steps=16 * 12, resume=True)
    assert not orphan.exists() and not list((tmp_path / "run").glob("*.tmp"))


@pytest.mark.parametrize("sig, said", [(signal.SIGINT, "interrupted"), (signal.SIGTERM, "interrupted by SIGTERM")])
def test_ctrl_c_or_sigterm_writes_a_checkpoint_and_the_resume_is_exact(tmp_path, sig, said):
    cfg = config_from_dict(BASE)
    train(cfg, tmp_path / "full", total_steps=16 * 30)
    before = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}  # (SIGINT: SIG_IGN in the background)

    def stop(step, row):
        if step == 16 * 15:  # between checkpoints (10, 20)
            os.kill(os.getpid(), sig)

    with pytest.raises(KeyboardInterrupt, match=f"^{said} at step 240.*--resume") as info:
        train(cfg, tmp_path / "part", total_steps=16 * 30, callback=stop)
    assert info.value.signum == sig
    assert torch.load(tmp_path / "part" / "checkpoint.pt", weights_only=True)["update"] == 15
    assert {s: signal.getsignal(s) for s in before} == before  # handlers given back
    train(cfg, tmp_path / "part", total_steps=16 * 30, resume=True)
    assert torch.equal(_flat(tmp_path / "part"), _flat(tmp_path / "full"))
    assert _rows(tmp_path / "part") == _rows(tmp_path / "full")


def test_cli_refuses_a_second_run_and_a_sweep_resumes_seed_by_seed(tmp_path, capsys):
    args = ["train", "--config", CONFIG, "--steps", "160", "--no-compile", "--quiet", "--no-plots"]
    out = tmp_path / "sweep"
    assert main([*args, "--seeds", "0", "--out", str(out), "--no-eval"]) == 0  # (the sweep's resume evaluates)
    assert main([*args, "--seeds", "0-1", "--out", str(out)]) == 2
    assert "already holds a run" in capsys.readouterr().err
    assert main([*args, "--seeds", "0-1", "--out", str(out), "--resume"]) == 0  # seed 1 never started: it starts
    assert (out / "seed_1" / "policy.pt").is_file()
    assert main([*args, "--seed", "0", "--out", str(out / "seed_0"), "--resume", "--override", "--steps", "320",
                 "--no-eval"]) == 0
    assert main([*args, "--out", str(out / "x"), "--override"]) == 2
    assert "--override only applies with --resume" in capsys.readouterr().err
    assert (out / "evaluation.json").is_file()
    (out / "loss_curves.png").write_text("the old sweep's")
    assert main([*args, "--seeds", "0-1", "--out", str(out), "--force", "--no-eval"]) == 0
    assert not (out / "evaluation.json").exists() and not (out / "loss_curves.png").exists()


def test_make_train_twice_just_works(tmp_path, capsys):
    import shlex
    import shutil
    import subprocess

    if shutil.which("make") is None:
        pytest.skip("no make")
    root = Path(__file__).parents[1]
    out = tmp_path / "default"
    for _ in range(2):  # the command `make train` runs, as make expands it at that moment
        cmd = subprocess.run(["make", "-s", "-n", "-o", ".venv/.installed", "-C", str(root), "train", f"OUT={out}",
                              "STEPS=160", f"TRAIN_CONFIG={CONFIG}"], capture_output=True, text=True, check=True).stdout
        argv = shlex.split(next(ln for ln in cmd.splitlines() if "a3cqp train" in ln))
        assert main(argv[argv.index("train"):] + ["--no-compile", "--quiet", "--no-plots"]) == 0
    assert "trained 160 steps" in capsys.readouterr().out


def test_an_output_path_is_checked_before_the_work_that_writes_it(tmp_path, monkeypatch) -> None:  # noqa: ANN001
    from a3cqp_rl.run_folder import check_output_path

    a_file = tmp_path / "a_file"
    a_file.write_text("")
    assert check_output_path(tmp_path / "new" / "deeper" / "r.json", "--json") == tmp_path / "new" / "deeper" / "r.json"
    assert check_output_path(tmp_path / "run", "--out", folder=True) == tmp_path / "run"
    assert check_output_path(tmp_path, "--out", folder=True) == tmp_path
    for path, folder, says in ((tmp_path, False, "--json .* is a folder, expected a file name"),
                               (a_file, True, "--json .* is a file, expected a folder"),
                               (a_file / "x.json", False, "is a file, not a folder"),
                               (a_file / "run" / "x", True, "is a file, not a folder")):
        with pytest.raises(RunFolderError, match=says):
            check_output_path(path, "--json", folder=folder)
    if os.geteuid() != 0:  # root may write anywhere
        locked = tmp_path / "locked"
        locked.mkdir(mode=0o500)
        with pytest.raises(RunFolderError, match="cannot write into"):
            check_output_path(locked / "x.json", "--json")
    # where the permission bits say yes but writing fails (root on a read-only or virtual file system: /proc)
    import errno
    import tempfile

    def read_only(*a, **k):  # noqa: ANN002, ANN003, ANN202
        raise OSError(errno.EROFS, "Read-only file system")

    with monkeypatch.context() as m:
        m.setattr(tempfile, "mkstemp", read_only)
        with pytest.raises(RunFolderError, match=r"--json .*r.json: cannot write into .* \(Read-only file system\)"):
            check_output_path(tmp_path / "r.json", "--json")
    check_output_path(tmp_path / "r.json", "--json")
    assert not [f for f in tmp_path.iterdir() if f.name.startswith(".a3cqp-write-check")]  # the probe cleans up


def test_a_run_that_fails_before_writing_anything_leaves_no_folder(tmp_path, capsys) -> None:  # noqa: ANN001
    out = tmp_path / "never"
    config = Path(__file__).resolve().parents[1] / "configs" / "panda_a2c_finetune.yaml"
    assert main(["train", "--config", str(config), "--out", str(out), "--set",
                 f"a2c.init_policy={tmp_path / 'nope.pt'}"]) == 2
    assert "checkpoint not found" in capsys.readouterr().err and not out.exists()
    kept = tmp_path / "kept"
    kept.mkdir()
    folder = RunFolder.open(kept)
    folder.close(failed=True)  # a folder that existed before stays
    assert kept.is_dir()
    fresh = RunFolder.open(tmp_path / "fresh")
    (fresh.path / "notes.txt").write_text("x")
    fresh.close(failed=True)  # one that holds something stays
    assert (tmp_path / "fresh" / "notes.txt").is_file()


def test_a_sigterm_stops_the_cli_with_a_checkpoint_and_exit_code_143(tmp_path):
    """`a3cqp train` as a job scheduler stops it: SIGTERM mid-run, a checkpoint, the resume hint, 128 + 15."""
    import subprocess
    import sys
    import time

    out = tmp_path / "run"
    cmd = [sys.executable, "-m", "a3cqp_rl.cli", "train", "--config", CONFIG, "--steps", "1000000000", "--out",
           str(out), "--no-compile", "--quiet", "--no-plots", "--set", "a2c.log_every=2", "--set",
           "a2c.checkpoint_every=1000000"]
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=Path(__file__).parents[1])
    try:
        deadline = time.monotonic() + 120
        while not ((out / "metrics.csv").is_file() and len((out / "metrics.csv").read_text().splitlines()) > 2):
            assert proc.poll() is None and time.monotonic() < deadline, proc.stderr.read() if proc.poll() else ""
            time.sleep(0.1)
        assert not (out / "checkpoint.pt").exists()  # none yet: checkpoint_every is far away
        proc.send_signal(signal.SIGTERM)
        _, err = proc.communicate(timeout=120)
    finally:
        proc.kill()
    assert proc.returncode == 143, err
    assert "interrupted by SIGTERM at step" in err and "continue with --resume" in err
    assert torch.load(out / "checkpoint.pt", weights_only=True)["update"] > 0
