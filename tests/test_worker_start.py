"""a3cqp_rl.worker_start: a pool worker forked from the server gets the parent's environment and working directory as
of the pool (not the server's), torch on one thread and the server's imports; where no fork server exists the
workers are spawned; `a3cqp evaluate --scene` starts the server only when it will run workers."""

from __future__ import annotations

import multiprocessing
import os
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import pytest

from a3cqp_rl import worker_start
from envs import evaluate_cli
from tests.process_probes import Finaliser

_SET_UP = None
ROOT = Path(__file__).resolve().parents[1]


if os.environ.get("A3CQP_TEST_TEARDOWN_FILE"):  # imported by a fork server (the teardown test below)
    _KEEP = Finaliser(os.environ["A3CQP_TEST_TEARDOWN_FILE"])
if os.environ.get("A3CQP_TEST_SLOW_IMPORT_FILE"):  # imported by a fork server (the early-exit test below)
    import time

    time.sleep(10.0)  # an import as slow as torchrl's, ten times over
    Path(os.environ["A3CQP_TEST_SLOW_IMPORT_FILE"]).write_text("imported")


def _set_up(marker: str) -> None:
    global _SET_UP
    _SET_UP = marker


def _probe() -> dict:
    import torch

    return {"cwd": os.getcwd(), "var": os.environ.get("A3CQP_WORKER_START_TEST"), "set_up": _SET_UP,
            "threads": torch.get_num_threads(), "server_setup": worker_start.SERVER_SETUP in sys.modules}


def _pool(ctx: multiprocessing.context.BaseContext) -> ProcessPoolExecutor:
    return worker_start.pool(1, ctx, f"{__name__}:_set_up", "ran")


def test_a_forked_worker_has_the_parents_environment_and_folder_and_torch_on_one_thread(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    if not worker_start.start(()):
        pytest.skip("this platform has no fork server (its workers are spawned: the next test)")
    # changed after the server started: a fork of it would otherwise keep the server's
    monkeypatch.setenv("A3CQP_WORKER_START_TEST", "set after the server started")
    monkeypatch.chdir(tmp_path)
    ctx = worker_start.context(())
    assert ctx.get_start_method() == "forkserver"
    with _pool(ctx) as pool:
        got = pool.submit(_probe).result(timeout=120)
    assert got == {"cwd": str(tmp_path), "var": "set after the server started", "set_up": "ran", "threads": 1,
                   "server_setup": True}


def _command(script: str, start: bool, **env: str) -> str:
    """stdout of `python -c "from a3cqp_rl import worker_start; <script>"`, with the fork server (preloading this
    module) started first if `start`, and `env` added. The output is read to its end, so the server, which holds it
    too, has ended."""
    if "forkserver" not in multiprocessing.get_all_start_methods():
        pytest.skip("this platform has no fork server")
    first = "assert worker_start.start(['tests.test_worker_start'])\n" if start else ""
    script = "from a3cqp_rl import worker_start\n" + first + script
    out = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, timeout=300,
                         env={**os.environ, **env})
    assert out.returncode == 0, out.stderr
    return out.stdout.strip()


def test_the_server_ends_without_its_teardown_when_the_command_ends(tmp_path: Path) -> None:
    """It would outlive the command by its teardown (~1 s with torch), holding the command's stdout open. (Started
    by the pool, as in a library call: `start` would also stop it at the command's exit.)"""
    marker = tmp_path / "server torn down"
    script = ("from concurrent.futures import ProcessPoolExecutor\n"
              "ctx = worker_start.context(['tests.test_worker_start'])\n"
              "with ProcessPoolExecutor(1, mp_context=ctx) as pool:\n"
              "    print(pool.submit(abs, -42).result())\n")
    assert _command(script, start=False, A3CQP_TEST_TEARDOWN_FILE=str(marker)) == "42"
    assert not marker.exists()


def test_a_command_that_ends_early_ends_the_server_still_importing(tmp_path: Path) -> None:
    """It would hold the command's stdout open until its imports ended (a bad argument waited for them)."""
    marker = tmp_path / "server imported"
    assert _command("print('ended before any worker')\n", start=True,
                    A3CQP_TEST_SLOW_IMPORT_FILE=str(marker)) == "ended before any worker"
    assert not marker.exists()  # stopped inside its imports, not after them


def test_without_a_fork_server_the_workers_are_spawned(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(multiprocessing, "get_all_start_methods", lambda: ["spawn"])
    assert worker_start.start(("envs.panda",)) is False
    ctx = worker_start.context(("envs.panda",))
    assert ctx.get_start_method() == "spawn"
    monkeypatch.setenv("A3CQP_WORKER_START_TEST", "spawned")
    with _pool(ctx) as pool:
        got = pool.submit(_probe).result(timeout=120)
    assert (got["var"], got["set_up"], got["server_setup"]) == ("spawned", "ran", False)


def test_the_environment_variable_chooses_spawn_and_a_bad_value_is_refused(monkeypatch: pytest.MonkeyPatch,
                                                                           capsys: pytest.CaptureFixture) -> None:
    monkeypatch.setenv("A3CQP_WORKER_START", "spawn")
    assert worker_start.context(()).get_start_method() == "spawn" and worker_start.start(()) is False
    monkeypatch.setenv("A3CQP_WORKER_START", "fork")
    with pytest.raises(ValueError, match="A3CQP_WORKER_START must be one of forkserver, spawn, got 'fork'"):
        worker_start.context(())
    monkeypatch.setattr(worker_start, "default_workers", lambda: 2)
    assert evaluate_cli.main(["--scene", "peg_in_hole", "--trials", "1"]) == 2
    assert capsys.readouterr().err == ("error: A3CQP_WORKER_START must be one of forkserver, spawn, got 'fork'\n")


@pytest.mark.parametrize("cores, argv, starts", [
    (2, ["--scene", "peg_in_hole"], True),
    (1, ["--scene", "peg_in_hole"], False),
    (2, ["--scene", "peg_in_hole", "--workers", "1"], False),
    (1, ["--scene", "peg_in_hole", "--workers=3"], True),
    (2, ["--scene", "peg_in_hole", "--workers", "many"], False),  # the parser's error, nothing started
    (2, ["--scene", "peg_in_hole", "--help"], False),
])
def test_the_scene_evaluation_starts_the_server_only_for_workers(monkeypatch: pytest.MonkeyPatch, cores: int,
                                                                 argv: list[str], starts: bool) -> None:
    monkeypatch.setattr(worker_start, "default_workers", lambda: cores)
    assert evaluate_cli._starts_workers(argv) is starts


@pytest.mark.slow
def test_the_benchmark_gets_the_same_sweep_from_forked_and_spawned_workers(capsys: pytest.CaptureFixture) -> None:
    from bench import worker_start as bench

    assert bench.main(["--quick"]) == 0
    out = capsys.readouterr().out
    assert "same results: yes" in out and "forkserver vs spawn:" in out
