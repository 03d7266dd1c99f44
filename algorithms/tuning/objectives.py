"""Objective functions for NSGA-II, registered by name (`nsga2.objective` in the config).

An objective maps a batch of decoded genomes (dicts gene name -> value) and the experiment config to objective
values [B, M], all minimised and finite (failures get large finite penalties, as paper 002 eq. 6 does). It must be
a pure function of its inputs, so that a value does not depend on which worker computed it or what else was in
its batch. Registered here: the ZDT1 and ZDT2 benchmarks (Zitzler, Deb, Thiele 2000), whose Pareto fronts are
known, to check the optimiser. Another module registers its own objectives with `@register(...)`; the config then
names it `module.path:name` (the module is imported, which registers `name`).
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from a3cqp_rl.config import ExperimentConfig, GeneConfig
from a3cqp_rl.exceptions import ConfigError

__all__ = ["Objective", "register", "get_objective", "OBJECTIVES", "zdt1", "zdt2"]


@dataclass(frozen=True)
class Objective:
    """A registered objective function and what the tuner needs to know about it."""

    name: str
    fn: Callable[[list[dict], ExperimentConfig], np.ndarray]
    """Genomes [B] and config -> values [B, M], minimised."""
    objectives: tuple[str, ...]
    """Names of the M values."""
    genes: tuple[GeneConfig, ...]
    """Default genome (used when the config lists no genes)."""
    chunk_size: int | None = None
    """Genomes per worker task (None: the batch split evenly over the workers)."""
    reference_point: tuple[float, ...] | None = None
    """Hypervolume reference (worse than every interesting point)."""
    reference_front: Callable[[int], np.ndarray] | None = None
    """n -> n points [n, M] of the known Pareto front (benchmarks only)."""
    to_config: Callable[[dict, ExperimentConfig, int], dict] | None = None
    """Genome, config and K -> the YAML mapping `a3cqp pareto --pick K` writes (default: genes and objectives)."""


OBJECTIVES: dict[str, Objective] = {}


def register(name: str, *, objectives: tuple[str, ...], genes: tuple[GeneConfig, ...], **options) -> Callable:
    """Decorator: register `fn` as objective `name` (options: the other fields of `Objective`)."""

    def deco(fn: Callable) -> Callable:
        OBJECTIVES[name] = Objective(name, fn, tuple(objectives), tuple(genes), **options)
        return fn

    return deco


def get_objective(name: str) -> Objective:
    """The objective a config names: a registered name, or `module.path:name` (imported first)."""
    if ":" in name:
        module, _, name = name.partition(":")
        try:
            importlib.import_module(module)
        except ImportError as exc:
            raise ConfigError(f"nsga2.objective: cannot import {module!r}: {exc}") from None
    if name not in OBJECTIVES:
        raise ConfigError(f"nsga2.objective: unknown objective {name!r}; registered: {sorted(OBJECTIVES)}")
    return OBJECTIVES[name]


# ------------------------------------------------------------------------------------------ ZDT benchmarks
def _zdt_x(genomes: list[dict]) -> np.ndarray:
    x = np.array([g["x"] for g in genomes], dtype=np.float64)
    if x.ndim != 2 or x.shape[1] < 2:
        raise ValueError(f"ZDT needs a vector gene 'x' of at least 2 entries, got shape {x.shape}")
    return x


def _zdt(x: np.ndarray, h: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """f1 = x1, g = 1 + 9 mean(x2..xn), f2 = g h(f1 / g)."""
    f1 = x[:, 0]
    g = 1.0 + 9.0 * x[:, 1:].mean(axis=1)
    return np.stack([f1, g * h(f1 / g)], axis=1)


_ZDT_GENES = (GeneConfig("x", 0.0, 1.0, size=30),)


@register("zdt1", objectives=("f1", "f2"), genes=_ZDT_GENES, reference_point=(1.1, 1.1),
          reference_front=lambda n: np.stack([np.linspace(0, 1, n), 1 - np.sqrt(np.linspace(0, 1, n))], axis=1))
def zdt1(genomes: list[dict], cfg: ExperimentConfig) -> np.ndarray:
    """ZDT1: convex front f2 = 1 - √f1 (x1 in [0, 1], the rest 0)."""
    return _zdt(_zdt_x(genomes), lambda r: 1.0 - np.sqrt(r))


@register("zdt2", objectives=("f1", "f2"), genes=_ZDT_GENES, reference_point=(1.1, 1.1),
          reference_front=lambda n: np.stack([np.linspace(0, 1, n), 1 - np.linspace(0, 1, n) ** 2], axis=1))
def zdt2(genomes: list[dict], cfg: ExperimentConfig) -> np.ndarray:
    """ZDT2: concave front f2 = 1 - f1² (x1 in [0, 1], the rest 0)."""
    return _zdt(_zdt_x(genomes), lambda r: 1.0 - r ** 2)
