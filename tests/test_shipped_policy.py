"""policies/point_mass_fig5_fd_1e6_seed0.pt, the learned controller of the Panda configs and of the README's Panda
tables, is what its point-mass config trains, bit for bit: the shipped file stands for the code, and a change to the
training's numbers shows here."""
from __future__ import annotations

from pathlib import Path

import torch
import yaml

from a3cqp_rl.checkpoint import load_checkpoint
from a3cqp_rl.config import load_config
from algorithms.a2c import train
from algorithms.policy import fingerprint, load_policy
from envs.panda_eval import free_motion_warning, guided_warning

ROOT = Path(__file__).resolve().parents[1]
SHIPPED = "policies/point_mass_fig5_fd_1e6_seed0.pt"


def test_the_panda_configs_name_the_shipped_policy_and_it_passes_the_transfer_checks() -> None:
    for name in ("panda_peg_in_hole", "panda_polishing", "panda_guidance"):
        assert yaml.safe_load((ROOT / "configs" / f"{name}.yaml").read_text())["panda"]["policy"] == SHIPPED, name
    finetune = yaml.safe_load((ROOT / "configs/panda_a2c_finetune.yaml").read_text())
    assert finetune["a2c"]["init_policy"] == SHIPPED
    policy = load_policy(ROOT / SHIPPED)
    assert free_motion_warning(policy) is None and guided_warning(policy) is None


def test_the_shipped_policy_is_what_its_config_trains(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.chdir(ROOT)  # a2c.select_config is relative to the working directory, as `make policy` runs it
    shipped = load_checkpoint(ROOT / SHIPPED, ("flat", "config"))
    cfg = load_config(ROOT / "configs/point_mass_a2c_fig5_fd_1e6.yaml")
    assert shipped["config"]["seed"] == cfg.seed == 0
    res = train(cfg, tmp_path)
    trained = load_checkpoint(res.policy_path, ("flat",))
    assert torch.equal(trained["flat"], shipped["flat"]), (
        f"training the config here gives parameters {fingerprint(load_policy(res.policy_path))}, the shipped policy is "
        f"{fingerprint(load_policy(ROOT / SHIPPED))}: the training's numbers changed (retrain and re-measure the Panda "
        "tables) or this machine rounds differently")
    assert fingerprint(load_policy(res.policy_path)) == fingerprint(load_policy(ROOT / SHIPPED))
    # the config chooses on the Panda (a2c.select_policy: panda): seed 0's last parameters inserted every peg
    kept = torch.load(res.policy_path, weights_only=True)["panda_selection"]
    assert kept["update"] == res.updates and kept["successes"] == kept["insertions"] == cfg.a2c.select_trials


def test_the_fingerprint_follows_the_parameters_not_the_files_other_entries(tmp_path: Path, capsys) -> None:
    from algorithms.policy import main

    data = torch.load(ROOT / SHIPPED, weights_only=True)
    same = tmp_path / "same.pt"
    torch.save({**data, "config": {**data["config"], "seed": 7}}, same)
    nudged = tmp_path / "nudged.pt"
    flat = data["flat"].clone()
    flat[123] = torch.nextafter(flat[123], torch.tensor(float("inf")))  # one parameter, one ulp
    torch.save({**data, "flat": flat}, nudged)
    assert fingerprint(load_policy(same)) == fingerprint(load_policy(ROOT / SHIPPED))
    assert fingerprint(load_policy(nudged)) != fingerprint(load_policy(ROOT / SHIPPED))
    assert main([str(ROOT / SHIPPED), str(same)]) == 0
    assert main([str(ROOT / SHIPPED), str(nudged)]) == 1
    assert "the parameters differ" in capsys.readouterr().out
    assert main([str(tmp_path / "missing.pt")]) == 2
