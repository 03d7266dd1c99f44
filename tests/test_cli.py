"""`a3cqp train` end to end: files, plots, resume, seed sweeps and clear errors."""

import json
import sys
from pathlib import Path

import pytest

from a3cqp_rl.cli import main
from a3cqp_rl.config import load_config

CONFIG = str(Path(__file__).parents[1] / "configs" / "point_mass_a2c.yaml")


def test_train_writes_results_and_plots_then_resumes(tmp_path, capsys):
    out = tmp_path / "run"
    assert main(["train", "--config", CONFIG, "--steps", "320", "--no-compile", "--quiet", "--out", str(out)]) == 0
    for name in ("policy.pt", "checkpoint.pt", "metrics.csv", "policy_map.png", "loss_curves.png", "regions.png"):
        assert (out / name).is_file(), name
    printed = capsys.readouterr().out
    assert str(out) in printed  # tells the user where results went
    assert "Fig. 5 regions " in printed and "w2 admittance" in printed  # and how the policy does on Fig. 5
    assert main(["train", "--config", CONFIG, "--steps", "640", "--no-compile", "--quiet", "--no-plots", "--no-eval",
                 "--out", str(out), "--resume"]) == 0
    assert "640" in capsys.readouterr().out


def test_seed_sweep_makes_one_folder_per_seed(tmp_path, capsys):
    out = tmp_path / "sweep"
    assert main(["train", "--config", CONFIG, "--steps", "160", "--no-compile", "--quiet", "--seeds", "0-1",
                 "--out", str(out)]) == 0
    assert (out / "seed_0" / "policy.pt").is_file() and (out / "seed_1" / "policy.pt").is_file()
    assert (out / "loss_curves.png").is_file() and (out / "regions.png").is_file()
    printed = capsys.readouterr().out
    assert "Fig. 5 regions (literal): all four on" in printed
    assert "| seed_0 |" in printed and "| seed_1 |" in printed and "best_return" in printed  # the robustness table
    assert (out / "evaluation.json").is_file()
    assert f"results in {out}/seed_*/: policy.pt" in printed  # where a sweep's policies are


def test_clear_errors(tmp_path, capsys):
    assert main(["train", "--config", str(tmp_path / "missing.yaml")]) == 2
    assert "not found" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text("a2c: {learning_rate: -1}\n")
    assert main(["train", "--config", str(bad)]) == 2
    assert "a2c.learning_rate" in capsys.readouterr().err
    assert main(["train", "--config", CONFIG, "--out", str(tmp_path / "none"), "--resume", "--no-compile"]) == 2
    assert "checkpoint not found" in capsys.readouterr().err


def test_final_message_says_when_no_episode_ended():
    from algorithms.train import _reward_text

    assert "no episode finished" in _reward_text(float("nan"))
    assert _reward_text(-12.345) == "last mean episode reward -12.35"


def test_default_config_works_from_any_directory(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)
    assert main(["train", "--steps", "512", "--no-compile", "--quiet", "--no-plots", "--no-eval", "--timings"]) == 0
    assert (tmp_path / "runs" / "point_mass_a2c_default" / "policy.pt").is_file()
    assert "timings: start-up " in capsys.readouterr().out  # what the train bench reads


def test_panda_evaluation_and_tuners_find_the_checkouts_configs_and_policy_from_any_directory(tmp_path, monkeypatch):
    from algorithms.tuning.runner import cli_config
    from envs import panda_eval

    monkeypatch.chdir(tmp_path)
    root = Path(__file__).resolve().parents[1]
    cfg_path = panda_eval._default_config("peg_in_hole")
    assert cfg_path == root / "configs" / "panda_peg_in_hole.yaml"
    policy = load_config(cfg_path).panda.policy
    assert not Path(policy).is_absolute()
    assert panda_eval._policy_file(policy, False, cfg_path) == root / policy
    with pytest.raises(FileNotFoundError):  # a --policy path is the user's: relative to the working directory only
        panda_eval._policy_file(policy, True, cfg_path)
    cfg, out = cli_config(None, None, False, "configs/ga_point_mass.yaml", "tune", "ga", {})
    assert cfg == load_config(root / "configs" / "ga_point_mass.yaml") and out == Path("runs/tune_ga_point_mass")
    # the working directory's own configs/ comes first
    (tmp_path / "configs").mkdir()
    (tmp_path / "configs" / "panda_peg_in_hole.yaml").write_text("panda: {policy: null}\n")
    assert panda_eval._default_config("peg_in_hole") == Path("configs") / "panda_peg_in_hole.yaml"


def test_file_errors_are_one_line_naming_the_file(tmp_path, capsys, monkeypatch):
    args = ["train", "--config", CONFIG, "--steps", "32", "--no-compile", "--quiet", "--no-plots", "--no-eval"]
    afile = tmp_path / "afile"
    afile.write_text("x")
    assert main([*args, "--out", str(afile)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"--out {afile} is a file" in err
    assert main([*args, "--out", str(afile / "sub")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"cannot write to {afile / 'sub'}" in err
    # a full disk while writing the checkpoint
    import errno

    import torch

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(torch, "save", full)
    assert main([*args, "--out", str(tmp_path / "full")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "checkpoint.pt: No space left on device" in err
    assert not list((tmp_path / "full").glob(".*.tmp"))
    monkeypatch.undo()
    # a corrupt metrics.csv on resume, a corrupt checkpoint: the file named, no torch advice
    run = tmp_path / "run"
    assert main([*args, "--out", str(run)]) == 0
    capsys.readouterr()
    (run / "metrics.csv").write_text("step,update\n16,one\n")
    assert main([*args, "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and f"{run / 'metrics.csv'} is not a metrics file" in err
    (run / "metrics.csv").write_text("step,update\n16,1,7\n")  # a row longer than the header: named, not a TypeError
    assert main(["plot", "loss-curves", str(run), "--out", str(tmp_path / "l.png")]) == 2
    assert "data row 1 has another number of fields than the header's 2" in capsys.readouterr().err
    (run / "checkpoint.pt").write_bytes(b"PK\x03\x04 not really")
    assert main([*args, "--out", str(run), "--resume"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and str(run / "checkpoint.pt") in err and "weights_only=False" not in err
    bad = tmp_path / "bad.yaml"
    bad.write_bytes(b"a2c: {ent_coef: \xff}\n")
    assert main(["train", "--config", str(bad)]) == 2
    assert f"{bad}: not UTF-8" in capsys.readouterr().err

    with pytest.raises(Exception, match="not UTF-8"):  # --debug: the traceback, for developers
        main(["train", "--config", str(bad), "--debug"])


def test_help_summary_keeps_the_whole_first_paragraph():
    from a3cqp_rl.cli import help_summary

    doc = "Train a\n    policy; one seed or a\n    sweep.\n\n    usage: ..."
    assert help_summary(doc) == "Train a policy; one seed or a sweep."
    assert help_summary(None) == ""


@pytest.mark.parametrize("command", ["train", "evaluate", "tune", "pareto", "plot", "demo"])
def test_every_command_help_ends_its_description(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    out = capsys.readouterr().out
    description = " ".join(out.split("\n\n")[1].split())  # usage, blank line, description
    assert description.endswith((".", ")")), description


def test_the_point_mass_help_names_every_panda_scene(capsys):
    from envs.scenarios import SCENES

    with pytest.raises(SystemExit):
        main(["evaluate", "--help"])
    out = capsys.readouterr().out
    assert "{" + ",".join(SCENES) + "}" in out


def test_train_set_overrides_reach_the_run_folders_config(tmp_path, capsys):
    """`a3cqp train --set KEY=VALUE` trains with the value and the run's config.yaml keeps it; a bad key is one line."""
    import yaml

    from algorithms.train import main as train_main

    out = tmp_path / "run"
    assert train_main(["--set", "seed=5", "--set", "a2c.n_steps=4", "--set", "a2c.learning_rate=3e-4", "--steps",
                       "400", "--out", str(out), "--no-compile", "--no-plots", "--no-eval", "--quiet"]) == 0
    kept = yaml.safe_load((out / "config.yaml").read_text())
    assert kept["seed"] == 5 and kept["a2c"]["n_steps"] == 4 and kept["a2c"]["learning_rate"] == 3e-4
    assert not kept["a2c"]["compile"]  # --no-compile merges with the --set a2c values
    capsys.readouterr()
    assert train_main(["--set", "a2c.n_step=4", "--out", str(tmp_path / "bad"), "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "with the command's overrides: unknown key(s) a2c.n_step" in err and "Traceback" not in err


def test_a_finished_run_resumed_keeps_its_log_a_shorter_one_is_refused_and_resume_reads_its_config(tmp_path, capsys):
    """`make train` twice resumes a finished run: its last metrics row (a partial logging window) must stay. A resume
    asking for fewer steps than were trained is refused; one without --config continues with OUT/config.yaml."""
    from algorithms.policy import load_policy

    out = tmp_path / "run"
    args = ["train", "--config", CONFIG, "--no-compile", "--quiet", "--no-plots", "--no-eval", "--out", str(out),
            "--set", "a2c.log_every=2"]
    assert main([*args, "--steps", "464"]) == 0  # 29 updates of 16 steps: the last row is not on a log_every boundary
    csv0, flat0 = (out / "metrics.csv").read_bytes(), load_policy(out).flat.clone()
    assert csv0.decode().strip().splitlines()[-1].split(",")[1] == "29"
    capsys.readouterr()
    assert main([*args, "--steps", "464", "--resume"]) == 0
    assert f"{out} had already trained its 464 steps: nothing left to train" in capsys.readouterr().out
    assert (out / "metrics.csv").read_bytes() == csv0 and bool((load_policy(out).flat == flat0).all())
    assert main([*args, "--steps", "160", "--resume"]) == 2
    assert "more than the 160 asked for" in capsys.readouterr().err
    assert (out / "metrics.csv").read_bytes() == csv0
    # the refusal leaves the run's config as it was: a plain resume still continues to the run's own length
    assert "total_steps: 464" in (out / "config.yaml").read_text()
    assert main(["train", "--out", str(out), "--resume", "--no-compile", "--quiet", "--no-plots", "--no-eval"]) == 0
    assert "had already trained its 464 steps" in capsys.readouterr().out
    # the README's `a3cqp train --out runs/paper --resume`: the run's own config, not the default one
    assert main(["train", "--out", str(out), "--resume", "--steps", "640", "--no-compile", "--quiet",
                 "--no-plots", "--no-eval"]) == 0


def test_a_diverging_run_stops_at_once_with_one_line_naming_the_step_and_the_lever(tmp_path, capsys):
    out = tmp_path / "dv"
    assert main(["train", "--config", CONFIG, "--steps", "3000000", "--set", "a2c.learning_rate=1e300",
                 "--no-compile", "--quiet", "--no-plots", "--no-eval", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "training diverged at step 16 (update 1): non-finite parameters; lower a2c.learning_rate (now 1e+300)" \
        in err
    assert "Traceback" not in err and not (out / "policy.pt").exists()


@pytest.mark.parametrize("args, said", [
    (["--seed", "99999999999999999999"], "seed 99999999999999999999 is outside [0, 2**63 - 1]"),
    (["--seed", "-1"], "seed -1 is outside"),
    (["--seeds", "1,1"], "names seed(s) [1] more than once"),
    (["--seeds", "0-2,2"], "names seed(s) [2] more than once"),
])
def test_bad_seeds_are_named_before_any_work(tmp_path, capsys, args, said):
    with pytest.raises(SystemExit):
        main(["train", "--config", CONFIG, "--steps", "160", "--out", str(tmp_path / "o"), *args])
    assert said in capsys.readouterr().err and not (tmp_path / "o").exists()
    bad = tmp_path / "seed.yaml"
    bad.write_text("seed: 99999999999999999999\n")
    with pytest.raises(Exception, match=r"seed: must be an integer in \[0, 2\*\*63 - 1\]"):
        load_config(bad)


def test_a_run_folder_named_like_a_baseline_gets_its_own_row(tmp_path, capsys):
    out = tmp_path / "ik_only"
    assert main(["train", "--config", CONFIG, "--steps", "160", "--no-compile", "--quiet", "--no-plots",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "| ik_only_run |" in printed and "| ik_only |" in printed
    assert (out / "evaluation.json").is_file()


def test_evaluate_names_the_panda_options_given_without_a_scene(capsys):
    with pytest.raises(SystemExit):
        main(["evaluate", "--trials", "2", "--controllers=ik"])
    err = capsys.readouterr().err
    assert "--controllers, --trials are for the Panda scenes: add --scene" in err
    with pytest.raises(SystemExit):
        main(["evaluate", "--bogus"])
    assert "unrecognized arguments: --bogus" in capsys.readouterr().err
    # and the other way round: the point mass's --episodes with a scene
    with pytest.raises(SystemExit):
        main(["evaluate", "--scene", "peg_in_hole", "--episodes", "3"])
    assert "--episodes is the point mass's: the scenes take --trials" in capsys.readouterr().err


def test_evaluate_checks_its_json_path_before_evaluating(tmp_path, capsys):
    assert main(["evaluate", "--episodes", "2", "--json", str(tmp_path)]) == 2
    err = capsys.readouterr().err
    assert "--json" in err and "is a folder, expected a file name" in err


def test_evaluate_json_dash_writes_the_metrics_alone_to_standard_output(capsys):
    assert main(["evaluate", "--episodes", "2", "--json", "-"]) == 0
    out, err = capsys.readouterr()
    doc = json.loads(out)  # one document, nothing else
    assert "checks" in doc and "Closed loop, point mass" in err and "wrote" not in err


def test_steps_are_recorded_so_a_plain_resume_continues_to_them(tmp_path, capsys):
    out = tmp_path / "short"
    base = ["train", "--config", CONFIG, "--no-compile", "--quiet", "--no-plots", "--no-eval", "--out", str(out)]
    assert main([*base, "--steps", "160"]) == 0
    assert load_config(out / "config.yaml").a2c.total_steps == 160
    capsys.readouterr()
    for again in ([base[0], *base[3:]], base):  # no --steps, with and without --config: the run's own length
        assert main([*again, "--resume"]) == 0
        assert "already trained its 160 steps" in capsys.readouterr().out
    assert main([*base, "--resume", "--steps", "320"]) == 0  # --steps changes it
    assert "trained steps 160 to 320 (resumed)" in capsys.readouterr().out
    assert load_config(out / "config.yaml").a2c.total_steps == 320
    assert main([*base, "--resume", "--set", "a2c.total_steps=480"]) == 0  # and so does --set
    assert "trained steps 320 to 480 (resumed)" in capsys.readouterr().out
    assert load_config(out / "config.yaml").a2c.total_steps == 480


@pytest.mark.parametrize("started", [["--seed", "3"], ["--set", "seed=3"]])
def test_a_plain_resume_continues_the_runs_own_seed(tmp_path, capsys, started):
    """A run started on a seed other than the config's resumes with neither --seed nor --override, on that seed."""
    out = tmp_path / "s3"
    base = ["train", "--config", CONFIG, "--no-compile", "--quiet", "--no-plots", "--no-eval", "--out", str(out)]
    assert main([*base, "--steps", "160", *started]) == 0
    capsys.readouterr()
    assert main(["train", "--out", str(out), "--resume", "--steps", "320", "--no-compile", "--quiet", "--no-plots",
                 "--no-eval"]) == 0
    assert "trained steps 160 to 320 (resumed)" in capsys.readouterr().out
    assert load_config(out / "config.yaml").seed == 3 and not (out / "overrides.log").exists()
    fresh = tmp_path / "fresh"  # the same 320 steps in one go: the resume lost and repeated nothing
    assert main([*base[:-1], str(fresh), "--steps", "320", *started]) == 0
    from algorithms.policy import load_policy

    assert bool((load_policy(fresh).flat == load_policy(out).flat).all())


def test_seed_given_twice_and_differently_is_refused(tmp_path, capsys):
    assert main(["train", "--config", CONFIG, "--steps", "160", "--seed", "5", "--set", "seed=3", "--quiet",
                 "--out", str(tmp_path / "o")]) == 2
    assert "--seed 5 and --set seed=3 disagree" in capsys.readouterr().err and not (tmp_path / "o").exists()


def test_shipped_configs_and_policies_are_found_from_another_folder(tmp_path, monkeypatch, capsys):
    monkeypatch.chdir(tmp_path)  # no configs/ or policies/ here
    assert main(["train", "--config", "configs/panda_a2c_finetune.yaml", "--steps", "1", "--no-compile",
                 "--quiet", "--no-plots", "--out", str(tmp_path / "ft"), "--set", "a2c.num_envs=1",
                 "--set", "a2c.n_steps=1", "--set", "a2c.select_policy=last"]) == 0
    assert "a2c: starting from" in capsys.readouterr().out


def test_a_reader_that_goes_away_neither_stops_the_command_nor_fails_it(tmp_path):
    """`a3cqp ... | head -1`: the rest of standard output is dropped, the command finishes and exits 0."""
    import subprocess
    import sys

    proc = subprocess.Popen([sys.executable, "-m", "a3cqp_rl.cli", "evaluate", "--episodes", "2", "--json",
                             str(tmp_path / "e.json")], stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            cwd=Path(CONFIG).parents[1])
    proc.stdout.close()  # gone before the first line
    err = proc.stderr.read().decode()
    assert proc.wait() == 0, err
    assert "Broken pipe" not in err and "Traceback" not in err
    assert "checks" in json.loads((tmp_path / "e.json").read_text())


def test_an_unknown_env_is_one_readable_line(tmp_path, capsys):
    assert main(["train", "--env", "Foo-v9", "--steps", "100", "--out", str(tmp_path / "e")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: ") and "invalid value(s): env: unknown environment 'Foo-v9'" in err
    assert ":;" not in err and "\n" not in err and "<defaults>" not in err


def test_a_commands_warning_is_one_plain_line(monkeypatch):
    import warnings

    from a3cqp_rl import cli

    monkeypatch.setattr(sys, "argv", ["a3cqp", "--help"])
    monkeypatch.setattr(sys, "stdout", sys.stdout)  # the console path wraps it; restored after the test
    monkeypatch.setattr(warnings, "formatwarning", warnings.formatwarning)
    assert cli.main() == 0
    said = warnings.formatwarning(UserWarning("a2c.average_last: cannot be rebuilt"), UserWarning,
                                  "/site-packages/algorithms/a2c_run.py", 77, "warnings.warn(...)")
    assert said == "warning: a2c.average_last: cannot be rebuilt\n"


def test_evaluate_names_a_policy_that_is_not_an_a3cqp_one_before_any_episode(tmp_path, capsys):
    from a3cqp_rl.config import config_from_dict
    from algorithms.a2c import train

    train(config_from_dict({"env": "Pendulum-v1", "a2c": {"compile": False}}), tmp_path / "pend", total_steps=64)
    assert main(["evaluate", "--policy", str(tmp_path / "pend"), "--episodes", "2"]) == 2
    err = capsys.readouterr().err
    assert "a policy of 3 observations and 1 actions; the point mass's agent needs 3 -> 4" in err


def test_the_top_level_help_lists_each_command_on_its_own_line(capsys):
    from a3cqp_rl.cli import COMMANDS

    assert main(["--help"]) == 0
    lines = capsys.readouterr().out.splitlines()
    for name, (_, text) in COMMANDS.items():
        assert any(line.startswith(f"  {name} ") and text.split()[0] in line for line in lines), name


def test_point_mass_evaluate_refuses_a_bad_json_path_before_importing_torch():
    import subprocess

    script = ("import sys, runpy\nsys.argv = ['a3cqp', 'evaluate', '--json', '/']\ntry:\n"
              "    runpy.run_module('a3cqp_rl.cli', run_name='__main__')\n"
              "except SystemExit as e:\n    print('rc', e.code, 'torch' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, cwd=Path(CONFIG).parents[1])
    assert "rc 2 False" in proc.stdout and "--json / is a folder" in proc.stderr
    with pytest.raises(SystemExit):
        main(["evaluate", "--episodes", "0"])


def test_the_panda_only_options_are_those_of_evaluate_scene_that_the_point_mass_lacks():
    from envs import evaluate_cli, panda_eval

    def flags(parser) -> set[str]:  # noqa: ANN001
        return {s for a in parser._actions for s in a.option_strings}

    assert evaluate_cli.PANDA_ONLY == flags(panda_eval._parser()) - flags(evaluate_cli._parser())


@pytest.mark.parametrize("argv", [["plot", "policy-map", "MISSING"], ["evaluate", "--episodes", "2", "--policy", "MISSING.pt"],
                                  ["train", "--config", "MISSING.yaml"]])
def test_a_commands_error_is_one_line_or_with_a3cqp_debug_its_traceback(argv, tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("A3CQP_DEBUG", raising=False)
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "MISSING" in err and "Traceback" not in err
    monkeypatch.setenv("A3CQP_DEBUG", "1")
    with pytest.raises(Exception, match="MISSING"):
        main(argv)
    monkeypatch.setenv("A3CQP_DEBUG", "0")
    assert main(argv) == 2


def test_a_resume_without_config_scores_the_run_with_its_own_reward(tmp_path, capsys):
    out = tmp_path / "paper"
    common = ["--no-compile", "--quiet", "--no-plots", "--out", str(out)]
    assert main(["train", "--config", CONFIG, "--steps", "160", "--no-eval", *common]) == 0
    capsys.readouterr()
    assert main(["train", "--resume", "--steps", "320", *common]) == 0  # the README's `--out runs/paper --resume`
    said = capsys.readouterr().out
    assert "returns with eq. 30 alpha = (0.5, 20, 2, 1)" in said, said[-600:]  # the run's, not the default (5, 40, 8, 1)
    assert json.loads((out / "evaluation.json").read_text())


def test_a_sweep_folder_an_episode_file_and_a_policy_file_given_to_the_wrong_command_are_named(tmp_path, capsys):
    import numpy as np

    from a3cqp_rl.checkpoint import save_atomic

    sweep = tmp_path / "sweep"
    for s in (0, 1):
        (sweep / f"seed_{s}").mkdir(parents=True)
        save_atomic({"flat": torch_zeros()}, sweep / f"seed_{s}" / "policy.pt")
    np.savez(tmp_path / "episode_learned.npz", time=np.zeros(3))
    cases = ((["evaluate", "--policy", str(sweep), "--episodes", "2"], "is a sweep of 2 run(s) (seed_0, seed_1)"),
             (["plot", "policy-map", str(sweep)], "pass its seed folders"),
             (["plot", "policy-map", str(tmp_path / "episode_learned.npz")], "is a numpy .npz archive"),
             (["plot", "episode", str(sweep / "seed_0" / "policy.pt")], "it is a torch file (a policy or checkpoint"))
    for argv, said in cases:
        assert main(argv) == 2, argv
        err = capsys.readouterr().err
        assert said in err and "Traceback" not in err and "inline_container" not in err, err


def torch_zeros():  # noqa: ANN201
    import torch

    return torch.zeros(3)
