"""Smoke tests of `a3cqp demo controller` and bench/controller.py (short runs; no timing asserts)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

from a3cqp_rl.demo import main as demo_main

ROOT = Path(__file__).resolve().parents[1]


def test_demo_controller_writes_a_png(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    png = tmp_path / "demo.png"
    assert demo_main(["controller", "--seconds", "0.05", "--out", str(png)]) == 0
    assert png.stat().st_size > 10_000 and png.read_bytes()[:4] == b"\x89PNG"
    assert f"wrote {png}" in capsys.readouterr().out


def test_demo_controller_refuses_a_time_too_short_to_plot_and_a_folder_as_its_png(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    import pytest

    for seconds in ("0", "-1", "nan", "0.0005"):
        with pytest.raises(SystemExit):
            demo_main(["controller", "--seconds", seconds])
        assert "--seconds must be at least 0.01" in capsys.readouterr().err
    assert demo_main(["controller", "--seconds", "0.01", "--out", str(tmp_path)]) == 2
    assert "is a folder, expected a file name" in capsys.readouterr().err
    assert demo_main(["controller", "--seconds", "0.01", "--out", str(tmp_path / "short.png")]) == 0
    capsys.readouterr()
    assert demo_main(["controller", "--seconds", "0.01", "--out", str(tmp_path / "plain")]) == 0
    assert f"wrote {tmp_path / 'plain.png'}" in capsys.readouterr().out  # the file's real name
    assert (tmp_path / "plain.png").is_file() and not (tmp_path / "plain").exists()


def test_bench_controller_quick_runs(capsys) -> None:  # noqa: ANN001
    spec = importlib.util.spec_from_file_location("bench_controller", ROOT / "bench" / "controller.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    assert module.main(["--quick", "--sizes", "1"]) == 0
    out = capsys.readouterr().out
    assert "RTF" in out and "<1000 µs" in out


def test_demo_controller_writes_under_runs_by_default(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    monkeypatch.chdir(tmp_path)
    assert demo_main(["controller", "--seconds", "0.02"]) == 0
    assert (tmp_path / "runs" / "demo_controller.png").is_file()
