"""Closed-loop evaluation of adaptation policies on the point mass (eq. 35), against fixed-weight baselines.

Every policy (a learned one, and the baselines below) runs on the *same* episodes: each scenario draws E episodes
once (`PointMassEnv` under a seed) and tiles them over the P policies, so one batched `agent_step` of P·E envs
steps them all. The scenarios hold operator and wall models that training does not use, so the table measures
generalisation, not memory:

  free            targets ±[5, 60] cm away, no forces                           final |e|, reached, time to 2 cm
  contact         a stiff, damped wall (20 kN/m, 300 N s/m) 20-40 cm away,       mean and peak contact force over
                  the target 1-5 mm behind its surface                          the last second, in the band
  operator        an operator grasps the mass and moves their hand 10-30 cm     mean |f_ope| while holding,
                  along a minimum-jerk path (1.5 s) through a spring-damper     final |e| after letting go
                  grip (300 N/m, 30 N s/m, at most f̄_ope); 1.7-2.2 s holds,
                  letting go for the last 1.5 s
  guided_contact  the same hand guides once (the first 3 s), away from the       mean |f_ope| while holding, contact
                  wall of `contact`; then the robot returns to it and presses   force over the last second, band

and the eq. 30 return per episode in each (with the evaluated config's reward weights), and its mean over the four
scenarios. Every episode starts at rest from the equal blend w = (1/3, 1/3, 1/3) and f_d = 0, so no policy starts
where it wants to be.

Baselines (policies from the eq. 26 observation to the eq. 29 rates, like the learned one): IK only, admittance
only, force control with f_d rising, the equal blend held, and a switching rule (the Fig. 5 pattern as a script:
admittance while an operator force is felt, force control with f_d rising in contact, IK otherwise).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import torch
from torch import Tensor

from a3cqp_rl.checkpoint import write_output_text
from a3cqp_rl.config import ExperimentConfig, check_fits, config_from_dict, config_to_dict
from envs.point_mass import PointMassEnv, agent_step, observe_state

__all__ = ["Scenario", "EVAL_SCENARIOS", "baseline_policies", "switching_rule", "evaluate", "EvalResult",
           "behaviour_checks", "CHECKS", "REACH_TOL", "BAND"]

Policy = Callable[[Tensor], Tensor]
"""Observation [B, 3] (eq. 26, float32) -> rates [B, 4] (ẇ1, ẇ2, ẇ3, ḟd), clipped to [-1, 1] by eq. 29."""

REACH_TOL = 0.02
"""free: a target counts as reached when the final |e| is below this [m]."""
BAND = (1.0, 30.0)
"""contact: the contact force must stay within [low, high] N over the last second (in contact, at most f̄_env)."""


@dataclass(frozen=True)
class Scenario:
    """One evaluation scenario: point-mass settings over the evaluated config, and which metrics it reports."""

    name: str
    description: str
    point_mass: dict
    """PointMassConfig overrides (one scenario kind, episode length, wall and operator models)."""
    metrics: tuple[str, ...]
    operator_until: float | None = None
    """Seconds after which the operator lets go for good (the rest of the schedule is zeroed); None: as drawn."""
    operator_away: bool = False
    """Hand moves always toward −x, away from the wall (a hand pulling into a wall cannot be yielded to)."""


_WALL = {"wall_min": 0.2, "wall_max": 0.4, "depth_min": 0.001, "depth_max": 0.005, "wall_stiffness": 20000.0,
         "wall_damping": 300.0}
_HAND = {"operator_model": "hand", "operator_hand_stiffness": 300.0, "operator_hand_damping": 30.0,
         "operator_goal_min": 0.1, "operator_goal_max": 0.3, "operator_move_time": 1.5, "operator_on_min": 1.7,
         "operator_on_max": 2.2, "operator_off_min": 0.3, "operator_off_max": 0.8, "operator_target_range": 0.02}

EVAL_SCENARIOS: dict[str, Scenario] = {
    s.name: s for s in (
        Scenario("free", "targets ±5-60 cm, no forces",
                 {"scenario_probs": {"free": 1.0}, "episode_steps": 300, "target_min": 0.05, "target_max": 0.6,
                  "target_speed_max": 0.0, "disturbance_max": 0.0},
                 ("final_e", "reached", "time_to_2cm", "return")),
        Scenario("contact", "stiff damped wall 20-40 cm away, target 1-5 mm behind it",
                 {"scenario_probs": {"wall": 1.0}, "episode_steps": 400, **_WALL},
                 ("force_mean", "force_peak", "in_band", "return")),
        Scenario("operator", "a hand grasps and moves the mass 10-30 cm (minimum jerk, 1.5 s), lets go for the last 1.5 s",
                 {"scenario_probs": {"operator": 1.0}, "episode_steps": 600, **_HAND},
                 ("f_ope_active", "final_e", "return"), operator_until=4.5),
        Scenario("guided_contact", "the hand moves the mass away from the wall of 'contact' once, then the robot returns "
                 "and presses",
                 {"scenario_probs": {"wall_operator": 1.0}, "episode_steps": 600, **_WALL, **_HAND},
                 ("f_ope_active", "force_mean", "in_band", "return"), operator_until=3.0, operator_away=True),
    )
}

METRIC_INFO = {
    "final_e": ("final |e|", "mm", 1e3), "reached": ("reached", "%", 100.0), "time_to_2cm": ("t to 2 cm", "s", 1.0),
    "force_mean": ("F mean", "N", 1.0), "force_peak": ("F peak", "N", 1.0), "in_band": ("in band", "%", 100.0),
    "f_ope_active": ("|f_ope|", "N", 1.0), "return": ("return", "", 1.0),
}
"""metric -> (column label, unit, factor from the JSON value (SI units, fractions) to the table's)."""


# ------------------------------------------------------------------------------------------------ baselines
def _constant(rates: tuple[float, float, float, float]) -> Policy:
    a = torch.tensor(rates, dtype=torch.float32)
    return lambda obs: a.expand(obs.shape[0], 4)


def switching_rule(f_ope_on: float = 0.002, f_env_on: float = 0.01) -> Policy:
    """The Fig. 5 pattern as a script, on the eq. 26 observation: admittance while |f_ope|/f̄_ope > `f_ope_on`, else
    force control with f_d rising while |f_env|/f̄_env > `f_env_on`, else IK with f_d falling (all rates ±1).

    The default thresholds (0.03 N and 0.3 N at Table II's bounds) scored the best mean return of a grid over
    f_ope_on in 0.002-0.1 and f_env_on in 0.01-0.05 on these scenarios (the returns differ by < 25 % over it)."""
    ik, adm, fc = (torch.tensor(r, dtype=torch.float32) for r in
                   ((1.0, -1.0, -1.0, -1.0), (-1.0, 1.0, -1.0, -1.0), (-1.0, -1.0, 1.0, 1.0)))

    def rule(obs: Tensor) -> Tensor:
        op = (obs[:, 2] > f_ope_on).unsqueeze(-1)
        contact = (obs[:, 1] > f_env_on).unsqueeze(-1)
        return torch.where(op, adm, torch.where(contact, fc, ik))

    return rule


def baseline_policies() -> dict[str, Policy]:
    """The fixed-weight baselines and the switching rule, by table name."""
    return {
        "ik_only": _constant((1.0, -1.0, -1.0, -1.0)),
        "admittance_only": _constant((-1.0, 1.0, -1.0, -1.0)),
        "force_control": _constant((-1.0, -1.0, 1.0, 1.0)),  # w3 -> 1, f_d rising to f̄_d
        "equal_blend": _constant((0.0, 0.0, 0.0, 0.0)),  # holds the start, w = 1/3 each, f_d = 0
        "switching_rule": switching_rule(),
    }


# ------------------------------------------------------------------------------------------------ evaluation
@dataclass
class EvalResult:
    """Per-policy, per-scenario metrics (SI units, fractions in [0, 1]); `return_mean` over the scenarios."""

    metrics: dict[str, dict[str, dict[str, float]]]
    """policy -> scenario -> metric -> value."""
    episodes: int
    seed: int
    scenarios: dict[str, str] = field(default_factory=dict)
    """scenario -> description."""
    alpha: tuple[float, ...] = ()
    """The eq. 30 reward weights of the returns."""

    @property
    def policies(self) -> list[str]:
        """Policy names, in the order given."""
        return list(self.metrics)

    def return_mean(self, policy: str) -> float:
        """Mean over the scenarios of the mean return per episode."""
        return sum(m["return"] for m in self.metrics[policy].values()) / len(self.metrics[policy])

    def to_dict(self) -> dict:
        """JSON-ready: settings, then per policy its scenarios' metrics and return_mean."""
        return {"episodes": self.episodes, "seed": self.seed, "alpha": list(self.alpha), "scenarios": self.scenarios,
                "reach_tol_m": REACH_TOL, "band_N": list(BAND),
                "policies": {p: {**{s: dict(m) for s, m in sc.items()}, "return_mean": self.return_mean(p)}
                             for p, sc in self.metrics.items()}}

    def write_json(self, path: str | Path, extra: dict | None = None) -> Path | None:
        """Write `to_dict()` (and the entries of `extra`) to `path` atomically ("-": standard output); NaN as null."""
        text = json.dumps(_nan_to_none({**self.to_dict(), **(extra or {})}), indent=1)
        return write_output_text(path, text + "\n")

    def table(self) -> str:
        """Two markdown tables, policies as rows: the behaviour metrics per scenario, then the returns."""
        scen = list(self.metrics[self.policies[0]])
        cols = [(s, m) for s in scen for m in EVAL_SCENARIOS[s].metrics if m != "return"]
        head = ["policy", *(f"{_SHORT.get(s, s)} {METRIC_INFO[m][0]} [{METRIC_INFO[m][1]}]" for s, m in cols)]
        behaviour = [[p, *(_cell(self.metrics[p][s][m], m) for s, m in cols)] for p in self.policies]
        rhead = ["policy", *(f"return {_SHORT.get(s, s)}" for s in scen), "mean return"]
        returns = [[p, *(f"{self.metrics[p][s]['return']:.1f}" for s in scen), f"{self.return_mean(p):.1f}"]
                   for p in self.policies]
        return _markdown(head, behaviour) + "\n\n" + _markdown(rhead, returns)


_SHORT = {"free": "free", "contact": "contact", "operator": "op.", "guided_contact": "guided"}


def _cell(value: float, metric: str) -> str:
    v = value * METRIC_INFO[metric][2]
    if math.isnan(v):
        return "–"
    return f"{v:.0f}" if METRIC_INFO[metric][1] in ("%", "mm") else f"{v:.2f}"


def _markdown(head: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|---|" + "---:|" * (len(head) - 1)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows])


def scenario_config(base: ExperimentConfig, scenario: Scenario) -> ExperimentConfig:
    """`base` (its dynamics, adaptation and reward) with the scenario's point-mass settings."""
    d = config_to_dict(base)
    d["point_mass"] = {**d["point_mass"], "random_initial_weights": False, **scenario.point_mass}
    return config_from_dict(d, f"<evaluation scenario {scenario.name}>")


@torch.no_grad()
def evaluate(policies: Mapping[str, Policy], episodes: int = 64, seed: int = 0, config: ExperimentConfig | None = None,
             scenarios: Sequence[str] | None = None) -> EvalResult:
    """Run every policy on the same `episodes` episodes of each scenario (one batched step for all); the metrics.

    `config` gives the point mass's dynamics, the adaptation law and the reward (paper defaults if None); the
    scenarios replace its episode settings. Deterministic under `seed`.
    """
    if not policies:
        raise ValueError("no policies to evaluate")
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    base = config or ExperimentConfig()
    names = list(scenarios or EVAL_SCENARIOS)
    unknown = [n for n in names if n not in EVAL_SCENARIOS]
    if unknown:
        raise ValueError(f"unknown scenario(s) {unknown}; choose from {list(EVAL_SCENARIOS)}")
    # each scenario holds every policy's copy of the episodes' records, float64 over T + 1 steps, about six times
    # over (measured 2026-12-01: 3.3 GB peak for 20,000 episodes of 5 policies)
    check_fits(episodes * (len(policies) + 2) * (base.point_mass.episode_steps + 1) * 8 * 6,
               f"{episodes:,} episodes per scenario for {len(policies)} policies", "fewer episodes")
    out: dict[str, dict[str, dict[str, float]]] = {p: {} for p in policies}
    for k, name in enumerate(names):
        sc = EVAL_SCENARIOS[name]
        per_policy = _run_scenario(policies, sc, scenario_config(base, sc), episodes, seed * 1009 + k)
        for p, m in per_policy.items():
            out[p][name] = m
    return EvalResult(out, episodes, seed, {n: EVAL_SCENARIOS[n].description for n in names},
                      tuple(float(a) for a in base.reward.alpha))


def _run_scenario(policies: Mapping[str, Policy], sc: Scenario, cfg: ExperimentConfig, E: int,
                  seed: int) -> dict[str, dict[str, float]]:
    P, T, pm, ad = len(policies), cfg.point_mass.episode_steps, cfg.point_mass, cfg.adaptation
    env = PointMassEnv(E, cfg, seed=seed)
    env.reset()
    state, schedule = env.functional()
    live = schedule[state["slot"], torch.arange(E)]  # [E, T + 1]
    if sc.operator_until is not None:
        live = live.clone()
        live[:, int(round(sc.operator_until / (pm.substeps * pm.physics_dt))):] = 0.0
    if sc.operator_away:
        live = -live.abs()
    # the same E episodes for each policy, at rest from the equal blend with f_d = 0
    state = {k: v.repeat(P, *([1] * (v.dim() - 1))) for k, v in state.items()}
    state["w_logits"] = torch.zeros_like(state["w_logits"])
    state["f_d"] = torch.zeros_like(state["f_d"])
    state["slot"] = torch.zeros_like(state["slot"])
    sched = live.repeat(P, 1).unsqueeze(0).contiguous()  # [1, P·E, T + 1]: slot 0
    active = (live[:, :T] != 0).T.repeat(1, P)  # [T, P·E]: the operator holds during step t
    fns = list(policies.values())
    e_tr, f_env_tr, f_ope_tr, rew = (torch.empty(T, P * E, dtype=torch.float64) for _ in range(4))
    for t in range(T):
        obs = observe_state(state, ad, dtype=torch.float32)
        act = torch.cat([_call(f, obs[i * E:(i + 1) * E], name) for i, (f, name) in enumerate(zip(fns, policies))])
        state, r = agent_step(state, act.to(torch.float64), sched, pm, ad, cfg.reward)
        e_tr[t], f_env_tr[t], f_ope_tr[t], rew[t] = state["target"] - state["x"], state["f_env"], state["f_ope"], r
    dt = pm.substeps * pm.physics_dt
    last = max(1, int(round(1.0 / dt)))  # the last second
    result = {}
    for i, name in enumerate(policies):
        sl = slice(i * E, (i + 1) * E)
        result[name] = _metrics(sc.metrics, e_tr[:, sl].abs(), f_env_tr[:, sl].abs(), f_ope_tr[:, sl].abs(),
                                rew[:, sl], active[:, sl], dt, last)
    return result


def _call(policy: Policy, obs: Tensor, name: str) -> Tensor:
    act = policy(obs)
    if act.shape != (obs.shape[0], 4):
        raise ValueError(f"policy {name!r} returned shape {tuple(act.shape)}, expected ({obs.shape[0]}, 4)")
    if not bool(torch.isfinite(act).all()):
        raise ValueError(f"policy {name!r} returned NaN or inf")
    return act


def _metrics(which: Sequence[str], e: Tensor, f_env: Tensor, f_ope: Tensor, rew: Tensor, active: Tensor, dt: float,
             last: int) -> dict[str, float]:
    """Episode metrics from traces [T, E] (|e| [m], |f_env|, |f_ope| [N], reward, operator holding)."""
    m: dict[str, float] = {}
    if "final_e" in which:
        m["final_e"] = e[-1].mean().item()
    if "reached" in which or "time_to_2cm" in which:
        inside = e < REACH_TOL
        m["reached"] = inside[-1].double().mean().item()
        # settling time: the first step from which |e| stays below the tolerance to the end
        stays = torch.flip(torch.cummin(torch.flip(inside.int(), [0]), dim=0).values, [0]).bool()  # [T, E]
        first = torch.where(stays.any(0), stays.int().argmax(0) + 1, -1).double() * dt
        ok = stays[-1]
        m["time_to_2cm"] = first[ok].mean().item() if bool(ok.any()) else float("nan")
    if "force_mean" in which or "force_peak" in which or "in_band" in which:
        tail = f_env[-last:]
        m["force_mean"] = tail.mean().item()
        m["force_peak"] = tail.max(0).values.mean().item()
        lo, hi = BAND
        m["in_band"] = ((tail.min(0).values >= lo) & (tail.max(0).values <= hi)).double().mean().item()
    if "f_ope_active" in which:
        m["f_ope_active"] = f_ope[active].mean().item() if bool(active.any()) else float("nan")
    m["return"] = rew.sum(0).mean().item()
    return {k: m[k] for k in which}


# ------------------------------------------------------------------------------------------------ checks
CHECKS = ("regions", "reaches", "bounded", "yields", "best_return")
"""Per-policy pass/fail columns of `behaviour_checks` (regions needs a region result passed in)."""
YIELD_RATIO = 1.5
YIELD_SLACK = 0.5
"""yields: mean |f_ope| while holding (operator scenario) <= YIELD_RATIO × admittance-only's + YIELD_SLACK [N]."""


def behaviour_checks(result: EvalResult, policy: str, literal_regions: int | None = None,
                     reference: str = "admittance_only", against: Sequence[str] | None = None) -> dict[str, bool]:
    """Pass/fail of `policy` on CHECKS.

    reaches: >= 90 % of the free targets within REACH_TOL at the end; bounded: >= 90 % of the contact episodes keep
    the force in BAND over the last second; yields: mean |f_ope| while the operator holds (operator scenario) at most
    YIELD_RATIO × `reference`'s + YIELD_SLACK; best_return: a higher mean return than each policy in `against`
    (default: every other policy in `result`); regions (with `literal_regions`, the number of literal Fig. 5 regions
    passed): all four.
    """
    m = result.metrics[policy]
    out = {}
    if literal_regions is not None:
        out["regions"] = literal_regions == 4
    out["reaches"] = m["free"]["reached"] >= 0.9 if "free" in m else False
    out["bounded"] = m["contact"]["in_band"] >= 0.9 if "contact" in m else False
    ref = result.metrics[reference]["operator"]["f_ope_active"] if reference in result.metrics else float("nan")
    out["yields"] = "operator" in m and m["operator"]["f_ope_active"] <= YIELD_RATIO * ref + YIELD_SLACK
    others = [p for p in (against if against is not None else result.policies) if p != policy]
    mine = result.return_mean(policy)
    out["best_return"] = all(mine > result.return_mean(p) for p in others)
    return out


def _nan_to_none(x):
    if isinstance(x, float) and math.isnan(x):
        return None
    if isinstance(x, dict):
        return {k: _nan_to_none(v) for k, v in x.items()}
    if isinstance(x, list):
        return [_nan_to_none(v) for v in x]
    return x


def scenario_names() -> tuple[str, ...]:
    """Names of the evaluation scenarios, in table order."""
    return tuple(EVAL_SCENARIOS)

