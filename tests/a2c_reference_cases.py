"""Training runs whose exact results tests/test_a2c_chunked.py pins (tests/data/a2c_reference.json).

`python -m tests.a2c_reference_cases` (from the project root) recomputes them and rewrites the JSON; the stored
numbers were computed by the per-update C iteration of commit 12f7139 (2026-11-25), before updates were batched
into one C call and the kernel was reorganised, so the test shows both changes kept every bit.
"""

from __future__ import annotations

import hashlib
import json
import subprocess
from pathlib import Path

from a3cqp_rl.config import load_config

REFERENCE = Path(__file__).with_name("data") / "a2c_reference.json"

CASES: dict[str, tuple[str, dict]] = {
    # the GA's trial setting (configs/ga_point_mass.yaml: Table IV, 4 envs) at the gene's n = 1, 4 and 32
    "ga_n1": ("configs/ga_point_mass.yaml", {"a2c.n_steps": 1, "a2c.total_steps": 12_000, "a2c.learning_rate": 1e-3}),
    "ga_n4": ("configs/ga_point_mass.yaml", {"a2c.n_steps": 4, "a2c.total_steps": 12_000, "a2c.learning_rate": 1e-3}),
    "ga_n32": ("configs/ga_point_mass.yaml", {"a2c.n_steps": 32, "a2c.total_steps": 12_800, "a2c.learning_rate": 1e-3}),
    # everything else the C iteration does: GAE, privileged critic, held noise, bound loss, weight averaging, odd
    # sizes (5 envs: 60 noise values per update), log rows off the episode grid
    "options": ("configs/point_mass_a2c_default.yaml",
                {"a2c.n_steps": 3, "a2c.num_envs": 5, "a2c.total_steps": 9_000, "a2c.noise_hold": 7,
                 "a2c.average_last": 0.3, "a2c.log_every": 37, "a2c.region_checks": 0, "point_mass.episode_steps": 250}),
    "shared": ("configs/ga_point_mass.yaml", {"a2c.n_steps": 2, "a2c.total_steps": 8_000, "a2c.network": "shared",
                                              "a2c.hidden": [32, 16, 8], "a2c.learning_rate": 1e-3}),
    # `make train`'s config, shortened
    "default": ("configs/point_mass_a2c_default.yaml", {"a2c.total_steps": 40_960, "a2c.log_every": 20,
                                                        "a2c.region_checks": 0}),
}


def case_config(name: str):
    """The ExperimentConfig of case `name`."""
    path, flat = CASES[name]
    nested: dict = {}
    for key, value in flat.items():
        section, field = key.split(".")
        nested.setdefault(section, {})[field] = value
    return load_config(Path(__file__).resolve().parents[1] / path, nested)


def digest(result, flat) -> dict:
    """What the test compares: the final parameters' bytes, every episode return, the last log row."""
    returns = [float(r) for r in result.episode_returns]
    return {"flat_sha256": hashlib.sha256(flat.numpy().tobytes()).hexdigest(),
            "flat_sum": float(flat.double().sum()),
            "returns_sha256": hashlib.sha256(json.dumps(returns).encode()).hexdigest(),
            "episodes": len(returns), "mean_return": sum(returns) / max(len(returns), 1),
            "final_metrics": {k: v for k, v in result.final_metrics.items() if k != "steps_per_second"}}


def compute(name: str, out_dir: Path | None = None, **train_kwargs) -> dict:
    """Train case `name` and digest it (the final parameters come from policy.pt or the checkpoint)."""
    import tempfile

    import torch

    from algorithms.a2c import train

    with tempfile.TemporaryDirectory() as tmp:
        out = Path(out_dir or tmp) / name
        res = train(case_config(name), out, **train_kwargs)
        flat = torch.load(out / "checkpoint.pt", weights_only=True)["flat"]
        policy = torch.load(out / "policy.pt", weights_only=True)["flat"]
        return {**digest(res, flat), "policy_sha256": hashlib.sha256(policy.numpy().tobytes()).hexdigest()}


def compiler() -> str:
    """The C compiler's first version line (the stored bits hold for the compiler that computed them)."""
    try:
        return subprocess.run(["cc", "--version"], capture_output=True, text=True, check=True).stdout.splitlines()[0]
    except (OSError, subprocess.CalledProcessError, IndexError):
        return "unknown"


if __name__ == "__main__":
    import platform

    data = {"compiler": compiler(), "machine": platform.machine(), "cases": {n: compute(n) for n in CASES}}
    REFERENCE.write_text(json.dumps(data, indent=1) + "\n")
    print(json.dumps(data, indent=1))
