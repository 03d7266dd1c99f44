"""Config loading: paper defaults, YAML files, and clear errors naming the file and key."""

from pathlib import Path

import pytest

from a3cqp_rl.config import ExperimentConfig, config_to_dict, load_config
from a3cqp_rl.exceptions import ConfigError

CONFIGS = sorted((Path(__file__).parents[1] / "configs").glob("*.yaml"))


def test_defaults_equal_paper_tables():
    c = ExperimentConfig()
    assert (c.controller.cp, c.controller.cv, c.controller.kp, c.controller.k_theta, c.controller.kq) == (3, 5, 150, 20, 10)
    assert (c.controller.lambda_d, c.controller.c_d, c.controller.epsilon, c.controller.mu) == (5, 5, 1e-4, 0.4)
    assert (c.adaptation.e_max, c.adaptation.f_env_max, c.adaptation.f_ope_max, c.adaptation.f_d_max) == (1, 30, 15, 20)
    assert (c.adaptation.sigma_w, c.adaptation.sigma_f) == (6, 10)
    assert c.reward.alpha == (0.5, 20, 2, 1)
    a = c.a2c
    assert (a.learning_rate, a.ent_coef, a.n_steps, a.rms_eps) == (4.25339846e-6, 3.371768978e-4, 4, 3.938214948e-5)
    assert (a.max_grad_norm, a.gamma, a.vf_coef, a.rms_alpha, a.num_envs) == (4.24498881, 0.99, 0.5, 0.99, 4)
    g = c.ga
    assert (g.num_generations, g.num_parents_mating, g.sol_per_pop, g.num_genes, g.keep_parents) == (50, 4, 8, 5, 1)
    assert (g.parent_selection_type, g.crossover_type, g.mutation_type, g.mutation_percent_genes) == ("sss", "single_point", "random", 10)
    assert c.point_mass.mass == 10 and c.point_mass.kv_value == pytest.approx(2 * 150**0.5)


@pytest.mark.parametrize("path", CONFIGS, ids=[p.name for p in CONFIGS])
def test_shipped_configs_load(path):
    cfg = load_config(path)
    assert isinstance(cfg, ExperimentConfig)


def test_default_training_config_is_the_one_make_train_and_the_cli_use():
    import re

    from algorithms.train import DEFAULT_CONFIG

    root = Path(__file__).parents[1]
    assert DEFAULT_CONFIG == root / "configs" / "point_mass_a2c_default.yaml"
    make = (root / "Makefile").read_text()
    assert re.search(r"^TRAIN_CONFIG \?= configs/point_mass_a2c_default\.yaml$", make, re.M)
    cfg = load_config(DEFAULT_CONFIG)
    assert cfg.env == "point_mass" and cfg.point_mass.operator_model == "drag"
    # the paper's Table IV run stays its own config, untouched
    paper = load_config(root / "configs" / "point_mass_a2c.yaml")
    assert (paper.a2c.learning_rate, paper.a2c.num_envs, paper.a2c.n_steps) == (4.25339846e-6, 4, 4)
    assert paper.reward.alpha == ExperimentConfig().reward.alpha


def test_default_training_config_comments_each_deviation_from_the_paper_tables():
    import yaml

    path = Path(__file__).parents[1] / "configs" / "point_mass_a2c_default.yaml"
    lines = path.read_text().splitlines()
    raw = yaml.safe_load(path.read_text())
    paper = ExperimentConfig()
    for section in ("a2c", "reward"):  # Tables IV and III
        for key, value in raw[section].items():
            if key in ("region_checks", "checkpoint_every", "log_every"):  # bookkeeping, not learning
                continue
            default = getattr(getattr(paper, section), key)
            if (tuple(value) if isinstance(value, list) else value) == default:
                continue
            line = next(ln for ln in lines if ln.strip().startswith(f"{key}:"))
            assert "#" in line, f"{section}.{key} deviates from the paper without a comment"


def test_roundtrip_and_overrides(tmp_path):
    import yaml

    p = tmp_path / "c.yaml"
    p.write_text(yaml.safe_dump({"a2c": {"learning_rate": "7e-4", "hidden": [32, 32]}, "seed": 3}))
    cfg = load_config(p, overrides={"a2c": {"n_steps": 5}})
    assert cfg.a2c.learning_rate == 7e-4 and cfg.a2c.hidden == (32, 32) and cfg.a2c.n_steps == 5 and cfg.seed == 3
    assert load_config(overrides=config_to_dict(cfg)) == cfg


@pytest.mark.parametrize(
    "text, key",
    [
        ("a2c: {learnin_rate: 0.1}", "a2c.learnin_rate"),
        ("a2c: {learning_rate: 0}", "a2c.learning_rate"),
        ("a2c: {learning_rate: -1e-3}", "a2c.learning_rate"),
        ("a2c: {gamma: 1.2}", "a2c.gamma"),
        ("a2c: {gamma: 0}", "a2c.gamma"),
        ("a2c: {n_steps: 2.5}", "a2c.n_steps"),
        ("a2c: {network: transformer}", "a2c.network"),
        ("a2c: {gae_lambda: 1.5}", "a2c.gae_lambda"),
        ("a2c: {noise_hold: 0}", "a2c.noise_hold"),
        ("a2c: {bound_coef: -1}", "a2c.bound_coef"),
        ("a2c: {critic: oracle}", "a2c.critic"),
        ("a2c: {critic: privileged, network: shared}", "a2c.critic"),
        ("point_mass: {mass: -10}", "point_mass.mass"),
        ("adaptation: {f_d_max: 0}", "adaptation.f_d_max"),
        ("adaptation: {e_max: .nan}", "adaptation.e_max"),
        ("reward: {alpha: [1, 2, 3]}", "reward.alpha"),
        ("reward: {alpha: [1, 2, -3, 4]}", "reward.alpha"),
        ("point_mass: {scenario_probs: {space: 1.0}}", "point_mass.scenario_probs"),
        ("point_mass: {wall_min: 0.2, wall_max: 0.1}", "point_mass.wall_min"),
        ("controller: {mu: yes}", "controller.mu"),
        ("ga: {num_parents_mating: 9}", "ga.num_parents_mating"),
        ("unknown_section: 1", "unknown_section"),
        ("point_mass: {episode_steps: 3}", "point_mass.episode_steps"),
        ("panda: {peg_in_hole: {insert_depth: 0.02}}", "panda.peg_in_hole.insert_depth"),
        ("panda: {peg_in_hole: {insert_depth: 0.04}}", "panda.peg_in_hole.insert_depth"),
        ("panda: {peg_in_hole: {hole_diameter: 0.019}}", "panda.peg_in_hole.hole_diameter"),
        ("panda: {peg_in_hole: {hole_diameter: 0.020}}", "panda.peg_in_hole.hole_diameter"),
        ("panda: {peg_in_hole: {hole_diameter: 0.2}}", "panda.peg_in_hole.hole_diameter"),
    ],
)
def test_bad_values_name_file_and_key(tmp_path, text, key):
    p = tmp_path / "bad.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(p)
    assert str(p) in str(info.value) and key in str(info.value)


def test_missing_and_non_mapping_files(tmp_path):
    with pytest.raises(ConfigError, match="not found"):
        load_config(tmp_path / "nope.yaml")
    p = tmp_path / "list.yaml"
    p.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="mapping"):
        load_config(p)
    p.write_text("a2c: {gamma: [unclosed")
    with pytest.raises(ConfigError, match="YAML"):
        load_config(p)


def _float_fields():
    """Every float field of the config (dotted), found by walking the dataclasses: new fields are covered too."""
    import dataclasses
    import typing

    def walk(cls, prefix):
        for f in dataclasses.fields(cls):
            tp = typing.get_type_hints(cls)[f.name]
            if dataclasses.is_dataclass(tp):
                yield from walk(tp, f"{prefix}{f.name}.")
            elif tp is float or tp == (float | None) or typing.get_origin(tp) is tuple and float in typing.get_args(tp):
                yield f"{prefix}{f.name}", tp

    return list(walk(ExperimentConfig, ""))


@pytest.mark.parametrize("bad", [".nan", ".inf", "-.inf"])
@pytest.mark.parametrize("key,tp", _float_fields(), ids=[k for k, _ in _float_fields()])
def test_every_float_field_must_be_finite(tmp_path, key, tp, bad):
    import typing

    *sections, name = key.split(".")
    value = f"[1.0, {bad}, 1.0, 1.0]" if typing.get_origin(tp) is tuple else bad
    text = "".join(f"{'  ' * i}{s}:\n" for i, s in enumerate(sections)) + f"{'  ' * len(sections)}{name}: {value}\n"
    p = tmp_path / "c.yaml"
    p.write_text(text)
    with pytest.raises(ConfigError, match="must be a finite number") as info:
        load_config(p)
    assert str(p) in str(info.value) and key in str(info.value)


def test_float_fields_found_include_the_reported_ones():
    keys = [k for k, _ in _float_fields()]
    assert len(keys) >= 35 and {"a2c.ent_coef", "point_mass.wall_damping", "point_mass.kv", "reward.alpha"} <= set(keys)


def test_env_names_registered_or_gymnasium(tmp_path):
    from a3cqp_rl.config import ENV_FACTORIES, config_from_dict

    assert "point_mass" in ENV_FACTORIES and config_from_dict({"env": "Pendulum-v1"}).env == "Pendulum-v1"
    with pytest.raises(ConfigError, match="env: unknown environment 'pointmass'"):
        config_from_dict({"env": "pointmass"})


def test_memory_estimate_refuses_a_million_envs_before_allocating():
    from a3cqp_rl.config import check_memory, config_from_dict, estimate_memory_bytes

    cfg = config_from_dict({"a2c": {"num_envs": 1_000_000}})
    assert estimate_memory_bytes(cfg) > 6 * 2**30  # measured: the run grew past 6 GB
    with pytest.raises(ConfigError, match="a2c.num_envs: 1000000 envs need about"):
        check_memory(cfg, available=8 * 2**30)
    check_memory(config_from_dict({}), available=8 * 2**30)  # the paper's 4 envs: fine
    wide = config_from_dict({"a2c": {"hidden": [100_000, 100_000]}})  # 1e10 weights: 40 GB each copy
    with pytest.raises(ConfigError, match=r"a2c.hidden: a network of hidden sizes \[100000, 100000\] need about"):
        check_memory(wide, available=64 * 2**30)
    check_memory(config_from_dict({"a2c": {"hidden": [256, 256]}}), available=8 * 2**30)
    from algorithms.a2c import train

    with pytest.raises(ConfigError, match="a2c.num_envs"):  # before any env is built (that would take minutes)
        train(config_from_dict({"a2c": {"num_envs": 10**9, "compile": False}}), None, total_steps=16)


def test_non_utf8_config_names_the_file(tmp_path):
    p = tmp_path / "latin1.yaml"
    p.write_bytes("seed: 0  # f\xfcr\n".encode("latin-1"))
    with pytest.raises(ConfigError, match=f"{p}: not UTF-8 text"):
        load_config(p)


def test_peg_config_reference_pulls_past_the_success_depth():
    """The shipped peg procedure's inserted pose lies well past the success depth and above the bore's floor, so an
    IK-led z axis still pulls a peg stalled just short of success (docs/panda.md, "What sets the insertion time")."""
    p = load_config(Path(__file__).resolve().parents[1] / "configs" / "panda_peg_in_hole.yaml").panda.peg_in_hole
    assert p.insert_depth - p.success_depth >= 0.01 - 1e-12
    assert p.hole_depth - p.insert_depth >= 0.005 - 1e-12


def test_an_unquoted_off_in_yaml_means_off_and_other_booleans_say_why_they_fail(tmp_path):
    path = tmp_path / "c.yaml"
    path.write_text("panda:\n  joint_limits_f_ext: off\n")  # YAML 1.1: false
    assert load_config(path).panda.joint_limits_f_ext == "off"
    path.write_text("panda:\n  idle_force: on\n")  # true, and idle_force has no "on"
    with pytest.raises(ConfigError, match="panda.idle_force: must be one of .*got True .*quote the word"):
        load_config(path)


def test_the_imperfect_sensing_peg_config_is_the_peg_config_plus_its_sensing():
    from a3cqp_rl.config import config_to_dict

    root = Path(__file__).resolve().parents[1] / "configs"
    plain = config_to_dict(load_config(root / "panda_peg_in_hole.yaml"))
    noisy = config_to_dict(load_config(root / "panda_peg_in_hole_sensors.yaml"))
    assert noisy["panda"]["sensors"]["tare_time"] > 0 and noisy["panda"]["observation_filter"] == "mean"
    assert noisy["panda"]["sensors"]["tare_time"] <= noisy["panda"]["peg_in_hole"]["settle_time"]
    for d in (plain, noisy):
        del d["panda"]["sensors"], d["panda"]["observation_filter"]
    assert plain == noisy


def test_a_base_file_is_read_first_and_the_config_applies_over_it_key_by_key(tmp_path):
    (tmp_path / "sub").mkdir()
    (tmp_path / "sub" / "eval.yaml").write_text("env: panda\npanda:\n  fd_axes: [z]\n  peg_in_hole:\n"
                                                 "    time_limit: 15.0\n    friction: 0.4\nadaptation:\n  f_d_max: 10.0\n")
    (tmp_path / "train.yaml").write_text("base: sub/eval.yaml\nseed: 3\npanda:\n  peg_in_hole:\n    time_limit: 12.0\n")
    cfg = load_config(tmp_path / "train.yaml")
    assert (cfg.seed, cfg.env, cfg.panda.fd_axes, cfg.adaptation.f_d_max) == (3, "panda", ("z",), 10.0)
    assert (cfg.panda.peg_in_hole.time_limit, cfg.panda.peg_in_hole.friction) == (12.0, 0.4)
    # a chain of bases, the nearest file winning
    (tmp_path / "top.yaml").write_text("base: train.yaml\nadaptation:\n  f_d_max: 5.0\n")
    top = load_config(tmp_path / "top.yaml")
    assert (top.seed, top.adaptation.f_d_max, top.panda.peg_in_hole.time_limit) == (3, 5.0, 12.0)


def test_a_folder_given_as_config_is_named(tmp_path):
    with pytest.raises(ConfigError, match="is a folder, expected a YAML config file"):
        load_config(tmp_path)


def test_a_missing_looping_or_malformed_base_is_a_config_error(tmp_path):
    (tmp_path / "a.yaml").write_text("base: nowhere.yaml\n")
    with pytest.raises(ConfigError, match=r"nowhere.yaml: config file not found \(the base of .*a.yaml\)"):
        load_config(tmp_path / "a.yaml")
    (tmp_path / "b.yaml").write_text("base: c.yaml\n")
    (tmp_path / "c.yaml").write_text("base: b.yaml\n")
    with pytest.raises(ConfigError, match="the files name each other as base"):
        load_config(tmp_path / "b.yaml")
    (tmp_path / "d.yaml").write_text("base: 3\n")
    with pytest.raises(ConfigError, match="base: expected the path of another config file, got 3"):
        load_config(tmp_path / "d.yaml")


@pytest.mark.parametrize("name", ["panda_a2c.yaml", "panda_a2c_finetune.yaml"])
def test_the_panda_trainings_train_in_the_env_their_evaluation_judges(name):
    """The Panda training configs: every panda and adaptation setting of the peg-in-hole evaluation config but the
    training episode's time limit (docs/panda.md, "Fine-tuning in the evaluation's env")."""
    from a3cqp_rl.config import config_to_dict

    root = Path(__file__).resolve().parents[1] / "configs"
    tr, ev = (config_to_dict(load_config(root / f)) for f in (name, "panda_peg_in_hole.yaml"))
    assert tr["env"] == "panda" and tr["adaptation"] == ev["adaptation"]
    assert tr["panda"]["peg_in_hole"].pop("time_limit") == 12.0
    ev["panda"]["peg_in_hole"].pop("time_limit")
    assert tr["panda"] == ev["panda"]
    assert tr["panda"]["ik_bound_tool_axis"] == 0.02 and tr["adaptation"]["f_d_max"] == 10.0


def test_set_overrides_parse_dotted_keys_with_yaml_values_and_name_bad_items():
    from a3cqp_rl.config import parse_overrides

    got = parse_overrides(["panda.blocked_force=2", "panda.fd_axes=[x, z]", "panda.ik_bound_blocked=null",
                           "a2c.learning_rate=1e-4", "seed=3", "seed=4"])
    assert got == {"panda": {"blocked_force": 2, "fd_axes": ["x", "z"], "ik_bound_blocked": None},
                   "a2c": {"learning_rate": "1e-4"}, "seed": 4}  # YAML 1.1 reads 1e-4 as text; the config converts it
    cfg = load_config(None, parse_overrides(["a2c.n_steps=7", "a2c.learning_rate=1e-4"]))
    assert cfg.a2c.n_steps == 7 and cfg.a2c.learning_rate == 1e-4
    for bad in ("seed", "=3", "a..b=1", "a2c.gamma=[1"):
        with pytest.raises(ConfigError, match="--set"):
            parse_overrides([bad])
    with pytest.raises(ConfigError, match=r"no '=' between KEY and VALUE; .*\(dotted for a section's: seed=3"):
        parse_overrides(["a2c.learning_rate"])
    with pytest.raises(ConfigError, match=r"the built-in defaults \(paper Tables I-V\) with the command's overrides: unknown key\(s\) a2c.gama"):
        load_config(None, parse_overrides(["a2c.gama=0.9"]))


def test_a_section_given_a_value_is_refused_whatever_else_fills_it(tmp_path):
    """`a2c: 5` in a file, or `--set a2c=3`, with other options filling a2c's keys: a ConfigError, never the defaults
    of a2c in silence (the merge used to replace the bad value with the options' section)."""
    from a3cqp_rl.config import parse_overrides

    (tmp_path / "bad.yaml").write_text("a2c: 5\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: a2c: expected a mapping, got int"):
        load_config(tmp_path / "bad.yaml", {"a2c": {"compile": False}})
    (tmp_path / "over.yaml").write_text("base: bad.yaml\na2c:\n  gamma: 0.9\n")
    with pytest.raises(ConfigError, match=r"over.yaml over its base .*bad.yaml: a2c: expected a mapping, got int"):
        load_config(tmp_path / "over.yaml")
    for items in (["a2c=3", "a2c.compile=false"], ["a2c.gamma=0.9", "a2c=3"]):
        with pytest.raises(ConfigError, match=r"--set 'a2c"):
            parse_overrides(items)


def test_advantage_normalisation_needs_two_samples_per_update():
    with pytest.raises(ConfigError, match="normalize_advantage: needs at least two samples per update"):
        load_config(None, {"a2c": {"normalize_advantage": True, "num_envs": 1, "n_steps": 1}})
    assert load_config(None, {"a2c": {"normalize_advantage": True, "num_envs": 1, "n_steps": 2}}).a2c.n_steps == 2


def test_a_bad_value_in_the_file_is_named_as_the_files_whatever_options_come_with_it(tmp_path):
    (tmp_path / "bad.yaml").write_text("a2c:\n  normalize_advantage: 'no'\n")
    with pytest.raises(ConfigError, match=r"bad.yaml: a2c.normalize_advantage") as exc:
        load_config(tmp_path / "bad.yaml", {"a2c": {"compile": False}})
    assert "with overrides" not in str(exc.value)
    with pytest.raises(ConfigError, match=r"(?s)bad.yaml with the command's overrides: .*a2c.gamma"):
        load_config(tmp_path / "bad.yaml", {"a2c": {"gamma": 2.0, "normalize_advantage": True}})
    (tmp_path / "g.yaml").write_text("a2c:\n  gamma: 2.0\n")  # an option may fix the file's value
    assert load_config(tmp_path / "g.yaml", {"a2c": {"gamma": 0.9}}).a2c.gamma == 0.9


def test_a_key_written_twice_in_a_file_is_refused_with_both_lines(tmp_path):
    (tmp_path / "dup.yaml").write_text("a2c:\n  learning_rate: 1e-3\n  gamma: 0.9\n  learning_rate: 2e-3\n")
    with pytest.raises(ConfigError, match=r"dup.yaml: a2c.learning_rate: given twice \(lines 2 and 4\)"):
        load_config(tmp_path / "dup.yaml")
    (tmp_path / "ok.yaml").write_text("a2c:\n  learning_rate: 1e-3\npanda:\n  learning_rate_unused: 1\n")
    with pytest.raises(ConfigError, match="unknown key"):  # the same name in two sections is no duplicate
        load_config(tmp_path / "ok.yaml")


def test_counts_in_scientific_notation_are_whole_numbers() -> None:
    from algorithms.train import _parser

    assert load_config(None, {"a2c": {"total_steps": "2e3"}}).a2c.total_steps == 2000  # YAML 1.1: a string
    assert load_config(None, {"a2c": {"total_steps": 2.0e3}}).a2c.total_steps == 2000
    with pytest.raises(ConfigError, match="expected an integer"):
        load_config(None, {"a2c": {"total_steps": "2.5e0"}})
    assert _parser().parse_args(["--steps", "2e5"]).steps == 200_000
    with pytest.raises(SystemExit):
        _parser().parse_args(["--steps", "1.5"])


def test_a_count_below_one_is_named_as_an_integer_and_a_length_as_a_number():
    from a3cqp_rl.config import config_from_dict

    with pytest.raises(ConfigError, match=r"panda.peg_in_hole.cycles: must be an integer >= 1, got 0"):
        config_from_dict({"panda": {"scene": "peg_in_hole", "peg_in_hole": {"cycles": 0}}})
    with pytest.raises(ConfigError, match=r"panda.peg_in_hole.time_limit: must be a finite number > 0, got 0.0"):
        config_from_dict({"panda": {"scene": "peg_in_hole", "peg_in_hole": {"time_limit": 0}}})


def test_a_misspelt_key_is_named_with_the_key_it_is_closest_to():
    from a3cqp_rl.config import config_from_dict

    with pytest.raises(ConfigError, match=r"unknown key\(s\) a2c\.learning_rat \(did you mean a2c\.learning_rate\?\), "
                                          r"a2c\.zzz; valid keys under a2c"):
        config_from_dict({"a2c": {"learning_rat": 1e-3, "zzz": 1}})
