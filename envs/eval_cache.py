"""A stopped `a3cqp evaluate --scene` resumes: each (policy, trial seed) result is kept in a folder as it ends.

`a3cqp evaluate --scene peg_in_hole --seeds 0-19 --cache DIR` (also with several `--policy`) writes DIR/<key>.npz
when a seed's evaluation ends. The key hashes everything that decides the numbers: the scene, trial count and seed,
the whole config, the controllers and fixed controllers, the policy's parameters (its fingerprint), the cycles, the
recorded trial, parking, workers and threads, and the source code of the simulation, controller and policy (so an
edited checkout measures anew). The same command run again reads the finished seeds back instead of simulating them,
so a sweep of twenty seeds (~20 min here) stopped at seed 15 loses at most one seed. Files are written atomically; a
file that cannot be read is measured again.
"""
from __future__ import annotations

import functools
import hashlib
import json
import logging
import zipfile
from dataclasses import asdict, is_dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from a3cqp_rl.checkpoint import write_atomic
from a3cqp_rl.config import config_to_dict
from envs.panda_report import EvalResult

logger = logging.getLogger(__name__)

_ROOT = Path(__file__).resolve().parents[1]
_CODE_DIRS = ("a3cqp_rl", "envs", "algorithms")
_CODE_SUFFIXES = (".py", ".c", ".h", ".xml", ".stl", ".obj")


@functools.lru_cache(maxsize=1)
def code_digest() -> str:
    """SHA-256 (16 hex digits) over the source and model files of a3cqp_rl, envs and algorithms in this checkout."""
    h = hashlib.sha256()
    for d in _CODE_DIRS:
        for path in sorted((_ROOT / d).rglob("*")):
            if path.suffix in _CODE_SUFFIXES and path.is_file() and "__pycache__" not in path.parts:
                h.update(str(path.relative_to(_ROOT)).encode())
                h.update(path.read_bytes())
    return h.hexdigest()[:16]


def result_key(scene: str, policy_fingerprint: str | None, trials: int, seed: int, config, **settings) -> dict:  # noqa: ANN001
    """What decides an evaluation's numbers, JSON-ready: `settings` are `evaluate`'s keyword arguments (controllers,
    cycles, fixed, sim_threads, workers, park, record_trial); `progress` does not count."""
    settings = {k: v for k, v in settings.items() if k != "progress"}
    fixed = [asdict(f) if is_dataclass(f) else repr(f) for f in settings.pop("fixed", ())]
    return {"scene": scene, "policy": policy_fingerprint, "trials": int(trials), "seed": int(seed),
            "config": config_to_dict(config) if config is not None else None, "fixed": fixed,
            **{k: list(v) if isinstance(v, tuple) else v for k, v in sorted(settings.items())}, "code": code_digest()}


def key_file(cache: Path, key: dict) -> Path:
    """The file of `key` in the folder `cache`: seed_S_<hash>.npz."""
    digest = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:16]
    return Path(cache) / f"seed_{key['seed']}_{digest}.npz"


def save(path: Path, key: dict, res) -> None:  # noqa: ANN001
    """Write an EvalResult's metrics, recorded episodes and timings to `path` atomically (`write_atomic`)."""
    arrays = {"key": np.array(json.dumps(key, sort_keys=True, default=str)), "scene": np.array(res.scene),
              "seconds": np.array(res.seconds), "sim_seconds": np.array(res.sim_seconds)}
    for group, data in (("m", res.metrics), ("e", res.episodes)):
        for c, fields in data.items():
            for k, v in fields.items():
                arrays[f"{group}|{c}|{k}"] = np.asarray(v)
    odd = [k for k, a in arrays.items() if a.dtype == object]
    if odd:  # such arrays need pickle, which `load` refuses: the seed would be measured again on every run
        logger.warning("evaluation cache: %s not written (no plain array for %s)", path, ", ".join(odd))
        return
    write_atomic(path, lambda f: np.savez_compressed(f, **arrays))


def load(path: Path, key: dict, seed: int):  # noqa: ANN201
    """The EvalResult kept in `path` if it was written for `key`; None if absent, unreadable or for another key."""
    if not path.is_file():
        return None
    try:
        with np.load(path, allow_pickle=False) as z:
            if json.loads(str(z["key"])) != json.loads(json.dumps(key, sort_keys=True, default=str)):
                return None
            metrics: dict = {}
            episodes: dict = {}
            for name in z.files:
                group, _, rest = name.partition("|")
                if group in ("m", "e"):
                    c, k = rest.split("|", 1)
                    v = z[name]
                    if group == "e" and v.dtype.kind == "U" and v.ndim == 0:
                        v = str(v)  # the scene's name, tool and MJCF text were strings
                    (metrics if group == "m" else episodes).setdefault(c, {})[k] = v
            res = EvalResult.from_metrics(str(z["scene"]), metrics, episodes, float(z["seconds"]),
                                          float(z["sim_seconds"]), (int(seed),))
            res.read_back = (int(seed),)
            return res
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, json.JSONDecodeError) as exc:
        # (a truncated .npz is a BadZipFile, an empty one an EOFError)
        logger.warning("evaluation cache: %s cannot be read (%s); measuring again", path, exc)
        return None


def _fingerprint(policy_path, kw: dict) -> str | None:  # noqa: ANN001
    """The parameters' fingerprint of the policy the learned controller runs (`policy_path`, else the config's
    panda.policy); None when no learned controller is evaluated."""
    if "learned" not in kw.get("controllers", ("learned",)):
        return None
    path = policy_path if policy_path is not None else getattr(getattr(kw.get("config"), "panda", None), "policy", None)
    if path is None:
        return None
    from algorithms.policy import fingerprint, load_policy

    return fingerprint(load_policy(path))


def cached(run: Callable, cache: str | Path | None, scene: str, policy_path, trials: int, seed: int,  # noqa: ANN001
           policy_fingerprint: str | None = None, log: Callable[[str], None] | None = None, **kw):  # noqa: ANN201
    """`run(scene, policy_path, trials, seed, **kw)` (panda_eval.evaluate), or its result read back from `cache`."""
    if cache is None:
        return run(scene, policy_path, trials, seed, **kw)
    if policy_fingerprint is None:
        policy_fingerprint = _fingerprint(policy_path, kw)
    key = result_key(scene, policy_fingerprint, trials, seed, kw.get("config"), **{k: v for k, v in kw.items()
                                                                                     if k != "config"})
    path = key_file(Path(cache), key)
    res = load(path, key, seed)
    if res is not None:
        if log is not None:
            log(f"seed {seed}: read back from {path} (measured before with the same settings)")
        return res
    res = run(scene, policy_path, trials, seed, **kw)
    save(path, key, res)
    return res
