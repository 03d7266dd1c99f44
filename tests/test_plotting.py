"""Policy maps and loss curves: right grid, right values, real image files."""

import pytest
import torch

from a3cqp_rl.config import config_from_dict
from a3cqp_rl.plotting import plot_loss_curves, plot_policy_map, policy_grid
from algorithms.a2c import train


def test_policy_grid_puts_state_variables_on_the_right_axes():
    def fake_policy(obs):  # action i = obs component (e, f_env, f_ope, 0)
        return torch.cat([obs, torch.zeros_like(obs[..., :1])], -1)

    xs, ys, act = policy_grid(fake_policy, x="f_ope", y="f_env", fixed="e", level=0.25, resolution=5)
    assert act.shape == (5, 5, 4)
    assert torch.allclose(act[..., 0], torch.full((5, 5), 0.25))
    assert torch.allclose(act[2, :, 1], torch.full((5,), 0.5))  # row index = y = f_env
    assert torch.allclose(act[:, 4, 2], torch.ones(5))  # column index = x = f_ope
    with pytest.raises(ValueError):
        policy_grid(fake_policy, x="e", y="e", fixed="f_ope")
    with pytest.raises(ValueError):
        policy_grid(fake_policy, level=1.5)


def test_plots_from_a_real_short_run(tmp_path):
    runs = []
    for seed in (0, 1):
        d = tmp_path / f"seed_{seed}"
        train(config_from_dict({"a2c": {"compile": False, "log_every": 10}, "seed": seed}), d, total_steps=16 * 30)
        runs.append(d)
    png = plot_policy_map(runs[0] / "policy.pt", tmp_path / "map.png", levels=(0.0, 0.5))
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    pdf = plot_loss_curves(runs, tmp_path / "loss.pdf")
    assert pdf.read_bytes()[:4] == b"%PDF"
    with pytest.raises(FileNotFoundError, match="metrics.csv"):
        plot_loss_curves([tmp_path], tmp_path / "x.png")


def test_plot_cli(tmp_path):
    from a3cqp_rl.cli import main

    train(config_from_dict({"a2c": {"compile": False, "log_every": 10}}), tmp_path / "r", total_steps=16 * 20)
    assert main(["plot", "policy-map", str(tmp_path / "r"), "--pdf"]) == 0
    assert (tmp_path / "r" / "policy_map.pdf").is_file()
    assert main(["plot", "loss-curves", str(tmp_path / "r"), "--out", str(tmp_path / "l.png")]) == 0
    assert main(["plot", "policy-map", str(tmp_path / "missing.pt")]) == 2
