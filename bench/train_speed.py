"""Training speed: Stable-Baselines3 A2C (the paper's setup) vs our A2C trainer, same task, same run.

Both train the A3CQP adaptation policy on the 1-DoF point mass (paper 000, eq. 35) with the paper's
Table IV settings (4 envs, n = 4 steps per env per update, RMSProp, lr 4.25e-6, ...) for N agent
steps (all envs together):

  - SB3: ``A2C("MlpPolicy", make_vec_env(PointMassGym, n_envs=4), ...)`` on `bench/point_mass_gym.py`,
    a gymnasium wrapper of the task (episodes from `envs.point_mass.PointMassEnv`, steps by the C point mass
    `envs.native`) that `tests/test_point_mass_gym.py` checks against the TorchRL env to 1e-9. Only ``learn()``
    is timed (construction excluded).
  - ours: ``algorithms.a2c.train(cfg, out_dir=None, total_steps=N, progress=False)``; its
    ``steps_per_second`` excludes the one-time ``torch.compile`` cost (``compile_seconds``). The
    projection adds the first run's whole one-time cost: train()'s wall time minus its steps at
    ``steps_per_second`` (compile, plus setup such as building and warming up the rollout).

Both run with ``torch.set_num_threads(1)``. With ``--repeats R`` the two are run alternately R times
(so they see the same machine load) and the medians are reported.

Start-up: ``a3cqp train`` (``python -m a3cqp_rl.cli train --timings``) in fresh processes, from process start to the
end of the first update (imports, config, env, the C library or torch.compile's first call), median of 3; and where
the loop's time went (its named timing blocks: iterate, regions, log, checkpoint).

Usage: python bench/train_speed.py [--steps N] [--ours-steps M] [--repeats R] [--quick] [--only sb3|ours]
                                   [--backend auto|torch|native]

Stable-Baselines3 is the optional ``bench`` extra; without it this prints how to install it and
exits 0.
"""

from __future__ import annotations

import argparse
import os
import statistics
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

from a3cqp_rl.cli import help_summary

_HERE = Path(__file__).resolve().parent
_ROOT = _HERE.parent
CONFIG = _ROOT / "configs" / "point_mass_a2c.yaml"
PROJECT_STEPS = 1_000_000

# SB3 A2C at the paper's Table IV settings (same numbers as configs/point_mass_a2c.yaml).
SB3_KWARGS = dict(
    learning_rate=4.25339846e-6,
    n_steps=4,
    gamma=0.99,
    ent_coef=3.371768978e-4,
    vf_coef=0.5,
    max_grad_norm=4.24498881,
    rms_prop_eps=3.938214948e-5,
    use_rms_prop=True,
    device="cpu",
    seed=0,
)
SB3_N_ENVS = 4


@dataclass
class Measurement:
    """Steps/s of each repeat for one trainer, plus one-time costs."""

    name: str
    rates: list[float] = field(default_factory=list)
    compile_seconds: list[float] = field(default_factory=list)
    setup_seconds: list[float] = field(default_factory=list)
    """Wall time of the call not explained by steps/s nor compile_seconds (construction, warm-ups)."""
    ratios: list[float] = field(default_factory=list)

    @property
    def rate(self) -> float:
        return statistics.median(self.rates)

    @property
    def one_time(self) -> float:
        """One-time cost in a fresh process: the first run's compile + setup (later runs hit the in-process cache)."""
        c = self.compile_seconds[0] if self.compile_seconds else 0.0
        return c + (self.setup_seconds[0] if self.setup_seconds else 0.0)

    def projected_seconds(self, steps: int = PROJECT_STEPS) -> float:
        return steps / self.rate + self.one_time


def _sb3_missing_message(exc: BaseException) -> str:
    return (
        f"stable-baselines3 is not installed ({exc}); it is the optional 'bench' extra.\n"
        "Install it with:  .venv/bin/pip install -c constraints.txt stable-baselines3\n"
        "  (or: .venv/bin/pip install -c constraints.txt -e '.[bench]')\n"
        "Skipping the training-speed benchmark."
    )


def _import_gym_env():
    if str(_HERE) not in sys.path:
        sys.path.insert(0, str(_HERE))
    from point_mass_gym import PointMassGym

    return PointMassGym


def run_sb3(cfg, steps: int) -> tuple[float, float]:
    """Train SB3 A2C for `steps` agent steps; returns (steps/s of learn(), learn() seconds)."""
    from stable_baselines3 import A2C
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.logger import Logger

    PointMassGym = _import_gym_env()
    vec_env = make_vec_env(PointMassGym, n_envs=SB3_N_ENVS, seed=SB3_KWARGS["seed"], env_kwargs={"config": cfg})
    try:
        model = A2C("MlpPolicy", vec_env, **SB3_KWARGS)
        # no folder: SB3's default logger makes an empty <tempdir>/SB3-<date> folder at every learn()
        model.set_logger(Logger(None, []))
        t0 = time.perf_counter()
        model.learn(total_timesteps=steps)
        elapsed = time.perf_counter() - t0
        done = int(model.num_timesteps)  # learn() stops at the first multiple of n_envs * n_steps >= steps
    finally:
        vec_env.close()
    return done / elapsed, elapsed


def env_only_rate(cfg, steps: int = 5000) -> float:
    """Steps/s of PointMassGym.step alone (fixed random actions, auto-reset): the env's share of SB3's cost."""
    import numpy as np

    env = _import_gym_env()(cfg)
    env.reset(seed=0)
    acts = np.random.default_rng(0).uniform(-1, 1, size=(steps, 4)).astype(np.float32)
    t0 = time.perf_counter()
    for a in acts:
        if env.step(a)[3]:
            env.reset()
    return steps / (time.perf_counter() - t0)


def run_ours(cfg, steps: int) -> tuple[float, float, float, int]:
    """Train with algorithms.a2c for `steps`; returns (steps/s excl. compile, compile s, wall s of train(), steps done)."""
    from algorithms.a2c import train

    t0 = time.perf_counter()
    result = train(cfg, out_dir=None, total_steps=steps, progress=False)
    wall = time.perf_counter() - t0
    done = int(getattr(result, "steps", steps))
    return float(result.steps_per_second), float(result.compile_seconds), wall, done


def startup(config: str, runs: int = 3, steps: int = 200_000) -> tuple[list[float], str]:
    """`a3cqp train --timings` in fresh processes: start-up seconds of each run, and the last run's timings line."""
    import re
    import tempfile

    values, line = [], ""
    for _ in range(runs):
        with tempfile.TemporaryDirectory() as tmp:
            out = subprocess.run([sys.executable, "-m", "a3cqp_rl.cli", "train", "--config", config, "--steps",
                                  str(steps), "--out", tmp, "--no-plots", "--quiet", "--timings"],
                                 capture_output=True, text=True, cwd=_ROOT, timeout=600)
        m = re.search(r"^timings: start-up ([0-9.]+) s.*$", out.stdout, re.M)
        if m is None:
            raise RuntimeError(f"a3cqp train printed no timings: {out.stdout[-500:]} {out.stderr[-500:]}")
        values.append(float(m.group(1)))
        line = m.group(0)
    return values, line


def _git_rev() -> str:
    try:
        out = subprocess.run(["git", "-C", str(_ROOT), "rev-parse", "--short", "HEAD"], capture_output=True,
                             text=True, timeout=5)
        return out.stdout.strip() or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def _fmt_duration(seconds: float) -> str:
    if seconds < 120:
        return f"{seconds:.1f} s"
    if seconds < 7200:
        return f"{seconds / 60:.1f} min"
    return f"{seconds / 3600:.2f} h"


def main(argv: list[str] | None = None) -> int:
    """Run the benchmark and print steps/s, the ratio ours/SB3 and projected 1e6-step times; returns 0."""
    p = argparse.ArgumentParser(description=help_summary(__doc__))
    p.add_argument("--steps", type=int, default=None, help="agent steps per training run (default 20000; 2000 with --quick)")
    p.add_argument("--repeats", type=int, default=None, help="runs of each trainer; medians reported (default 3; 1 with --quick)")
    p.add_argument("--quick", action="store_true", help="short smoke run: 2000 steps, 1 repeat")
    p.add_argument("--only", choices=("sb3", "ours"), default=None, help="run only one side")
    p.add_argument("--config", default=str(CONFIG), help="experiment config for both trainers")
    p.add_argument("--ours-steps", type=int, default=None,
                   help="agent steps per run of ours (default 5 x --steps: it is ~30x faster, so short runs are noisy)")
    p.add_argument("--backend", choices=("auto", "torch", "native"), default=None,
                   help="a2c.backend for ours (default: the config's; auto = C at the paper's 16 samples/update)")
    args = p.parse_args(argv)
    steps = args.steps if args.steps is not None else (2000 if args.quick else 20000)
    ours_steps = args.ours_steps if args.ours_steps is not None else 5 * steps
    repeats = args.repeats if args.repeats is not None else (1 if args.quick else 3)
    if steps < 16 or repeats < 1:
        p.error("--steps must be >= 16 (one update of 4 envs x 4 steps) and --repeats >= 1")

    try:
        import stable_baselines3

        sb3_version = stable_baselines3.__version__
    except ImportError as exc:
        if args.only != "ours":
            print(_sb3_missing_message(exc))
            return 0
        sb3_version = "not installed"

    import gymnasium
    import torch

    import a3cqp_rl
    from a3cqp_rl.config import load_config

    torch.set_num_threads(1)
    # no Fig. 5 region checks (~20 ms each): SB3 runs no evaluation during learn() either
    cfg = load_config(args.config, {"a2c": {"region_checks": 0, **({"backend": args.backend} if args.backend else {})}})
    a = cfg.a2c
    print("Training speed: A2C on the point mass (paper 000, eq. 35), paper settings (Table IV)")
    print(f"  {a.num_envs} envs x n={a.n_steps} steps per update ({a.num_envs * a.n_steps} samples/update), "
          f"{steps:,} agent steps per SB3 run and {ours_steps:,} per run of ours, {repeats} run(s) each (median), "
          f"config {args.config}, a2c.backend {a.backend}, a2c.region_checks 0")
    print(f"  torch.set_num_threads(1) for both (this machine: {os.cpu_count()} CPU cores, "
          f"load average at start {os.getloadavg()[0]:.2f})")
    print(f"  versions: stable-baselines3 {sb3_version}, a3cqp-rl {a3cqp_rl.__version__} "
          f"(git {_git_rev()}), torch {torch.__version__}, gymnasium {gymnasium.__version__}, "
          f"python {sys.version.split()[0]}")
    if (a.num_envs, a.n_steps) != (SB3_N_ENVS, SB3_KWARGS["n_steps"]):
        print(f"  WARNING: config has {a.num_envs} envs x n={a.n_steps}; SB3 runs the paper's "
              f"{SB3_N_ENVS} x {SB3_KWARGS['n_steps']}, so the two do different work")

    sb3 = Measurement("SB3 A2C (MlpPolicy, DummyVecEnv of PointMassGym)")
    ours = Measurement("ours (algorithms.a2c.train)")
    ours_error: str | None = None
    for i in range(repeats):
        if args.only != "ours":
            rate, elapsed = run_sb3(cfg, steps)
            sb3.rates.append(rate)
            print(f"  run {i + 1}: SB3  {rate:>10,.0f} steps/s  (learn() {elapsed:.2f} s)", flush=True)
        if args.only != "sb3" and ours_error is None:
            try:
                rate, comp, wall, done = run_ours(cfg, ours_steps)
            except ImportError as exc:
                ours_error = f"algorithms.a2c.train not available ({exc})"
                continue
            ours.rates.append(rate)
            ours.compile_seconds.append(comp)
            setup = max(wall - comp - done / rate, 0.0)  # construction, warm-ups, anything else outside the steps
            ours.setup_seconds.append(setup)
            if sb3.rates:
                ours.ratios.append(rate / sb3.rates[-1])  # pairs run back to back see similar load
            print(f"  run {i + 1}: ours {rate:>10,.0f} steps/s  (train() {wall:.2f} s = {done / rate:.2f} s steps "
                  f"+ {comp:.2f} s compile_seconds + {setup:.2f} s other setup)", flush=True)

    if sb3.rates:
        env_rate = env_only_rate(cfg)
        print(f"  PointMassGym.step alone: {env_rate:,.0f} steps/s, i.e. ~{100 * sb3.rate / env_rate:.0f} % of "
              "SB3's training time is the environment")
    print()
    print(f"{'trainer':<50} {'steps/s':>10} {'one-time':>10} {'1e6 steps (projected)':>22}")
    for m in (sb3, ours):
        if m.rates:
            print(f"{m.name:<50} {m.rate:>10,.0f} {m.one_time:>9.1f}s {_fmt_duration(m.projected_seconds()):>22}")
    if ours_error:
        print(f"ours: skipped: {ours_error}")
    if sb3.rates and ours.rates:
        pair = f", median of the per-run ratios {statistics.median(ours.ratios):.2f}x" if len(ours.ratios) > 1 else ""
        print(f"ratio ours/SB3 (median steps/s, one-time costs excluded): {ours.rate / sb3.rate:.2f}x{pair}")
        print(f"projected 1e6-step time SB3/ours (one-time costs included): "
              f"{sb3.projected_seconds() / ours.projected_seconds():.2f}x")
    print("one-time = first run's torch.compile + setup inside train() (excluded from steps/s, included in the "
          "projection; later runs in this process reuse the compiled code). SB3: construction not timed.")
    if args.only != "sb3":
        make_config = str(_ROOT / "configs" / "point_mass_a2c_default.yaml")  # what `make train` runs
        values, line = startup(make_config)
        print(f"start-up of `a3cqp train` ({Path(make_config).name}, 2e5 steps, fresh processes): median "
              f"{statistics.median(values):.2f} s (runs: {', '.join(f'{v:.2f}' for v in values)}), process start to the "
              f"end of the first update; last run's {line}")
    print(f"load average at end {os.getloadavg()[0]:.2f} (other processes share the cores: compare ratios, "
          "not absolute rates, across runs)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
