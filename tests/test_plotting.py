"""Policy maps and loss curves: right grid, right values, real image files."""

import numpy as np
import pytest
import torch

from a3cqp_rl.config import config_from_dict
from a3cqp_rl.plotting import plot_loss_curves, plot_policy_map, plot_region_history, policy_grid, region_history
from algorithms.a2c import load_policy, train


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
    png = plot_policy_map(load_policy(runs[0] / "policy.pt"), tmp_path / "map.png", levels=(0.0, 0.5))
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
    assert main(["plot", "regions", str(tmp_path / "r"), "--pdf"]) == 0
    assert (tmp_path / "r" / "regions.pdf").read_bytes()[:4] == b"%PDF"  # one run: inside it, as train writes it
    assert main(["plot", "policy-map", str(tmp_path / "missing.pt")]) == 2


def test_plot_cli_names_and_paths_that_do_not_collide_or_trace_back(tmp_path, capsys):
    from a3cqp_rl.cli import main

    for seed in (0, 1):
        train(config_from_dict({"a2c": {"compile": False, "log_every": 10}, "seed": seed}), tmp_path / f"seed_{seed}",
              total_steps=16 * 20)
    runs = [str(tmp_path / "seed_0"), str(tmp_path / "seed_1")]
    assert main(["plot", "loss-curves", *runs]) == 0  # several runs: beside them (the sweep's folder)
    assert (tmp_path / "loss_curves.png").is_file()
    assert main(["plot", "loss-curves", runs[1]]) == 0
    assert (tmp_path / "seed_1" / "loss_curves.png").is_file()
    (tmp_path / "loss_curves.png").unlink()  # the sweep's folder itself stands for its seeds
    assert main(["plot", "loss-curves", str(tmp_path), "--out", str(tmp_path / "sweep.png")]) == 0
    assert (tmp_path / "sweep.png").is_file()
    from a3cqp_rl.plotting.cli import _expand_sweeps

    (tmp_path / "seed_10").mkdir()
    (tmp_path / "seed_10" / "metrics.csv").write_text("")
    assert _expand_sweeps([str(tmp_path)]) == [*runs, str(tmp_path / "seed_10")]  # 10 after 1: seed order
    # the last parameters' map does not replace the kept policy's
    assert main(["plot", "policy-map", runs[0]]) == 0
    assert main(["plot", "policy-map", f"{runs[0]}/checkpoint.pt"]) == 0
    assert (tmp_path / "seed_0" / "policy_map.png").is_file()
    assert (tmp_path / "seed_0" / "policy_map_checkpoint.png").is_file()
    # --x e alone: f_env stays on y and f_ope, the state left, is the one held at the levels
    assert main(["plot", "policy-map", runs[0], "--x", "e", "--out", str(tmp_path / "e_fenv.png")]) == 0
    assert (tmp_path / "e_fenv.png").is_file()
    capsys.readouterr()
    (tmp_path / "afile").write_text("")
    for args, said in ((["policy-map", runs[0], "--out", str(tmp_path / "afile" / "m.png")], "is a file, not a folder"),
                       (["policy-map", runs[0], "--levels", "abc"], "--levels 'abc': expected comma-separated"),
                       (["policy-map", runs[0], "--levels", "0,2"], "level must be in [0, 1]"),
                       (["policy-map", runs[0], "--x", "e", "--y", "e"], "--x and --y both name e"),
                       (["policy-map", runs[0], "--x", "e", "--fixed", "e"], "--fixed e is also on an axis")):
        assert main(["plot", *args]) == 2
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err


def test_a_policy_map_needs_the_four_a3cqp_actions():
    with pytest.raises(ValueError, match="gives 1 action.* a policy map draws the A3CQP policy's 4"):
        policy_grid(lambda obs: obs[..., :1])


def _region_csv(path, steps, flags):
    """A metrics.csv with only the columns region_history reads; flags [S, 4] (w2, w3, fd, w1) or None (no check)."""
    path.mkdir(parents=True)
    lines = ["step,regions_ok,region_w2,region_w3,region_fd,region_w1"]
    for s, f in zip(steps, flags):
        lines.append(f"{s},nan,nan,nan,nan,nan" if f is None else f"{s},{sum(f)},{','.join(map(str, f))}")
    (path / "metrics.csv").write_text("\n".join(lines) + "\n")


def test_region_history_fractions_by_hand(tmp_path):
    _region_csv(tmp_path / "a", [10, 20, 30, 40], [[1, 1, 1, 1], None, [0, 1, 1, 1], [1, 1, 1, 1]])
    _region_csv(tmp_path / "b", [10, 20, 30, 40], [[0, 1, 0, 1], None, [0, 1, 1, 1], None])  # b's last check: 30
    steps, frac = region_history([tmp_path / "a", tmp_path / "b"])
    assert steps.tolist() == [10, 30, 40]  # the unchecked row is skipped
    # rows: w2, w3, fd, w1, all four; at 40 run b counts with its check at 30
    assert frac.tolist() == [[0.5, 0.0, 0.5], [1.0, 1.0, 1.0], [0.5, 1.0, 1.0], [1.0, 1.0, 1.0], [0.5, 0.0, 0.5]]
    png = plot_region_history([tmp_path / "a", tmp_path / "b"], tmp_path / "r.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    _region_csv(tmp_path / "none", [10, 20], [None, None])
    with pytest.raises(ValueError, match="no Fig. 5 region checks"):
        region_history([tmp_path / "none"])


def test_region_checks_follow_the_config(tmp_path):
    import csv

    def checked(run, **a2c):
        train(config_from_dict({"a2c": {"compile": False, "log_every": 5, **a2c}}), tmp_path / run, total_steps=16 * 52)
        with (tmp_path / run / "metrics.csv").open() as f:
            return [int(r["update"]) for r in csv.DictReader(f) if r["regions_ok"] != "nan"]

    # 10 full log rows + a partial last one; 3 checks asked: every 4th row, and the last
    assert checked("three", region_checks=3) == [20, 40, 52]
    assert checked("off", region_checks=0) == []
    with pytest.raises(ValueError, match="region_checks"):
        config_from_dict({"a2c": {"region_checks": -1}})


def _metrics_csv(path, steps, losses, env="point_mass"):
    path.mkdir(parents=True)
    rows = ["step,policy_loss,value_loss,episode_reward", *(f"{s},{v},{2 * v},nan" for s, v in zip(steps, losses))]
    (path / "metrics.csv").write_text("\n".join(rows) + "\n")
    (path / "config.yaml").write_text(f"env: {env}\n")


def test_loss_curves_put_runs_of_other_grids_on_their_union_whatever_the_order(tmp_path):
    from a3cqp_rl.plotting.loss_curves import aligned, read_runs

    _metrics_csv(tmp_path / "short", [100], [5.0])  # one row: it once set the grid of every other run
    _metrics_csv(tmp_path / "long", [50, 100, 150, 200], [1.0, 2.0, 3.0, 4.0])
    a = read_runs([tmp_path / "short", tmp_path / "long"])
    steps, ys = aligned(a, "policy_loss")
    assert steps.tolist() == [50, 100, 150, 200]
    assert ys[1].tolist() == [1.0, 2.0, 3.0, 4.0] and ys[0, 1] == 5.0 and np.isnan(ys[0, [0, 2, 3]]).all()
    steps_b, ys_b = aligned(read_runs([tmp_path / "long", tmp_path / "short"]), "policy_loss")
    assert steps_b.tolist() == steps.tolist() and np.array_equal(ys_b[::-1], ys, equal_nan=True)
    with pytest.warns(UserWarning, match="short/metrics.csv has 1 row"):
        assert plot_loss_curves([tmp_path / "short", tmp_path / "long"], tmp_path / "l.png").is_file()
    with pytest.raises(ValueError, match="given twice"):
        read_runs([tmp_path / "long", tmp_path / "x" / ".." / "long"])
    _metrics_csv(tmp_path / "pend", [100, 200], [1.0, 2.0], env="Pendulum-v1")
    with pytest.raises(ValueError, match=r"different envs: .*pend \(Pendulum-v1\)"):
        read_runs([tmp_path / "long", tmp_path / "pend"])


def test_region_history_counts_every_runs_checks_in_any_order(tmp_path):
    _region_csv(tmp_path / "a", [10, 30], [[1, 1, 1, 1], [1, 1, 1, 1]])
    _region_csv(tmp_path / "b", [20, 40], [[0, 1, 1, 1], [1, 1, 1, 1]])
    steps, frac = region_history([tmp_path / "a", tmp_path / "b"])
    assert steps.tolist() == [10, 20, 30, 40]
    assert frac[4].tolist() == [0.5, 0.5, 0.5, 1.0]  # b not yet checked at 10 counts as not passed
    steps_b, frac_b = region_history([tmp_path / "b", tmp_path / "a"])
    assert steps_b.tolist() == steps.tolist() and np.array_equal(frac_b, frac)
