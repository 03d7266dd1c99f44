"""`make peg` / `make fig7` evaluate the shipped policy the Panda configs name (no training); `make policy` trains it
here and compares."""
from __future__ import annotations

import os
import re
import shutil
import subprocess
from pathlib import Path

import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
MAKEFILE = (ROOT / "Makefile").read_text()


def test_the_makefile_evaluates_the_policy_the_panda_configs_name() -> None:
    m = re.search(r"^PANDA_POLICY := (\S+)$", MAKEFILE, re.M)
    assert m, "PANDA_POLICY not set in the Makefile"
    for scene in ("peg_in_hole", "polishing", "guidance"):
        cfg = yaml.safe_load((ROOT / "configs" / f"panda_{scene}.yaml").read_text())
        assert cfg["panda"]["policy"] == m.group(1), scene
    assert (ROOT / m.group(1)).is_file(), "the shipped policy is missing"
    # `make policy` trains the config that policy comes from and compares the two
    rule = re.search(r"^runs/pm_default/policy.pt:.*\n\t(.*)$", MAKEFILE, re.M)
    assert rule and "train --config configs/point_mass_a2c_fig5_fd_1e6.yaml --out $(@D)" in rule.group(1)
    compare = re.search(r"^policy: runs/pm_default/policy.pt\n\t(.*)$", MAKEFILE, re.M)
    assert compare and "-m algorithms.policy runs/pm_default/policy.pt $(PANDA_POLICY)" in compare.group(1)


@pytest.mark.skipif(shutil.which("make") is None, reason="needs make")
def test_make_peg_dry_run_evaluates_without_training(tmp_path: Path) -> None:
    for f in ("Makefile", "configs/point_mass_a2c_fig5_fd_1e6.yaml", "pyproject.toml", "constraints.txt", "setup.py",
              "a3cqp_rl/native_sources.py"):
        (tmp_path / f).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy(ROOT / f, tmp_path / f)
    (tmp_path / ".venv").mkdir()
    (tmp_path / ".venv/.installed").touch()  # newer than its prerequisites: no install in the dry run

    def dry(target: str, *assign: str) -> list[str]:
        # under `make test` the parent make's variables would turn on "Entering directory" lines
        env = {k: v for k, v in os.environ.items() if k not in ("MAKEFLAGS", "MAKELEVEL", "MFLAGS", "MAKEOVERRIDES")}
        out = subprocess.run(["make", "--no-print-directory", "-n", target, *assign], cwd=tmp_path, capture_output=True,
                             text=True, check=True, env=env)
        return [ln for ln in out.stdout.splitlines() if ln.strip()]

    lines = dry("peg")
    assert len(lines) == 1 and "a3cqp evaluate --scene peg_in_hole --trials 26 --seed 0" in lines[0], lines
    pooled = dry("peg", "PEG_SEEDS=0,3-10")
    assert len(pooled) == 1 and "--seeds 0,3-10 --cache runs/peg_cache --out runs/peg26_seeds0,3-10" in pooled[0]
    assert "--seed " not in pooled[0]
    fig7 = dry("fig7")
    assert len(fig7) == 3 and "--cycles 3" in fig7[0]
    assert all("a3cqp plot episode runs/peg_fig7" in ln for ln in fig7[1:])
    # `make policy` trains only when its run has no policy yet, then compares it with the shipped file
    lines = dry("policy")
    assert len(lines) == 2, lines
    assert "a3cqp train --config configs/point_mass_a2c_fig5_fd_1e6.yaml --out runs/pm_default --no-plots" in lines[0]
    assert "-m algorithms.policy runs/pm_default/policy.pt policies/point_mass_fig5_fd_1e6_seed0.pt" in lines[1]
    (tmp_path / "runs/pm_default").mkdir(parents=True)
    (tmp_path / "runs/pm_default/policy.pt").touch()
    assert len(dry("policy")) == 1
    # an edited config does not retrain a finished run (order-only prerequisite)
    (tmp_path / "configs/point_mass_a2c_fig5_fd_1e6.yaml").touch()
    assert len(dry("policy")) == 1
