"""Fixed controllers on the Panda env: per-arm gains, priority levels, constant task weights and f_d.

A `FixedControllerConfig` (a3cqp_rl/config.py) is one fixed controller: what NSGA-II tunes (paper 002, offline) and
what `a3cqp pareto --pick K` writes. `FixedArms` gives each arm of a PandaEnv one of them (or None: an arm that keeps
Table I gains, one level and whatever weights its policy or script sets), through the env's controller factory
(a3cqp_rl.control.population.PopulationController) and `PandaEnv.hold_weights` every agent step:

    arms = FixedArms([cfg_a, cfg_a, cfg_b, None])
    env = PandaEnv(4, config, controller_factory=arms.controller_factory)
    ...  each step: arms.hold(env)  (before env.step)
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from a3cqp_rl.config import ControllerConfig, FixedControllerConfig
from a3cqp_rl.control import ControllerOptions
from a3cqp_rl.control.population import TASKS, PopulationController, RobotGains

__all__ = ["FixedArms"]

class FixedArms:
    """Per-arm fixed controllers for a PandaEnv of len(configs) arms (None: not fixed, Table I and one level)."""

    def __init__(self, configs: Sequence[FixedControllerConfig | None]) -> None:
        self.configs = list(configs)
        n = len(self.configs)
        self.mask = np.array([c is not None for c in self.configs], dtype=bool)
        """Arms whose weights and f_d this object holds [N]."""
        self.weights = np.zeros((n, 6, 3))
        """Local weights [N, 6, 3] (columns IK, AC, FC) of the fixed arms."""
        self.f_d = np.zeros((n, 6))
        """Local desired wrench [N, 6]: f_d along the tool axis (z) of the fixed arms."""
        self.levels = np.ones((n, len(TASKS)), dtype=np.int64)
        """Priority levels [N, 5] (TASKS order, 0 = off)."""
        for i, c in enumerate(self.configs):
            if c is None:
                continue
            self.weights[i] = np.asarray(c.weight_matrix())
            self.f_d[i, 2] = c.f_d
            self.levels[i] = c.level_row()
        self.controller: PopulationController | None = None
        """The controller the env built through `controller_factory`."""

    def gains(self, config: ControllerConfig, options: ControllerOptions) -> RobotGains:
        """Per-arm gains: the fixed arms' own, the env's config (Table I) for the others."""
        base = RobotGains.uniform(len(self.configs), config, options)
        cols = {f: getattr(base, f).copy() for f in RobotGains.__dataclass_fields__}
        for i, c in enumerate(self.configs):
            if c is not None:
                for f in cols:
                    cols[f][i] = getattr(c, f)
        return RobotGains(**cols)

    def controller_factory(self, n: int, model=None, config: ControllerConfig | None = None,  # noqa: ANN001
                           options: ControllerOptions | None = None) -> PopulationController:
        """PandaEnv's controller_factory: a PopulationController with these arms' gains and levels."""
        if n != len(self.configs):
            raise ValueError(f"FixedArms holds {len(self.configs)} arms, the env has {n}")
        config, options = config or ControllerConfig(), options or ControllerOptions()
        self.controller = PopulationController(n, model=model, config=config, options=options,
                                               gains=self.gains(config, options), levels=self.levels)
        return self.controller

    def hold(self, env) -> None:  # noqa: ANN001
        """Hold the fixed arms' weights and f_d for the next env step (the others run eq. 29 of their action)."""
        env.hold_weights(self.mask, self.weights, self.f_d)

    def merge(self, weights: np.ndarray, f_d: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Copies of (weights [N, 6, 3], f_d [N, 6]) with the fixed arms' rows replaced by theirs."""
        W, F = np.array(weights, dtype=np.float64), np.array(f_d, dtype=np.float64)
        W[self.mask], F[self.mask] = self.weights[self.mask], self.f_d[self.mask]
        return W, F
