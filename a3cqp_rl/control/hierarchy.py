"""Strict task priorities (paper 002, eq. 2-4): tasks in levels 1..3 or off, solved as a cascade of batched QPs.

A stack S = (w_a T_a + w_b T_b) / (w_c T_c) / ... (eq. 3) has soft weights inside a level and strict priorities
between levels. Level k's QP (eq. 2) minimises its tasks' weighted residuals Σ_i ‖A_i x − b_i‖²_{W_i} + r‖x‖²
subject to the limits G x ≤ h and to every level above keeping its optimal residuals ("A_j u_j = A_j u", paper 002
section II). The cascade solves it in the null space of the levels above instead of adding their rows as equality
constraints (why: see `solve_cascade`); every level is one batched `solve_qp` call for all N robots.

`Hierarchy` maps task names to levels (validated); `level_from_selector` is eq. 4 (a genome's level selector
l ∈ [0, 1] to a level or off). The controller takes `levels=` and runs `solve_cascade` when there is more than one.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
import torch

from a3cqp_rl.control.arrays import Array, const, mm, mv
from a3cqp_rl.control.exceptions import InvalidLevelError
from a3cqp_rl.qp import QPSolution, solve_qp

__all__ = ["MAX_LEVEL", "RANK_TOL", "Hierarchy", "CascadeSolution", "level_from_selector", "levels_from_selectors",
           "solve_cascade"]

MAX_LEVEL = 3
"""Levels are 1 (highest priority) .. MAX_LEVEL, as in paper 002 (eq. 4; "one could optimize for as many levels")."""
RANK_TOL = 1e-10
"""Eigenvalues of the stacked higher-level Hessian Σ A_jᵀ W_j A_j below RANK_TOL × its largest one count as zero:
those directions are left to the lower levels (a higher level's cost then moves by at most ~RANK_TOL relative)."""
_ROW_TOL = 1e-9
"""A limit row whose null-space part has less than this fraction of its norm is dropped from a lower level's QP
(the solver normalises rows, so a rounding-error row would otherwise become a constraint in a random direction)."""


def level_from_selector(selector: float) -> int | None:
    """Paper 002 eq. 4: a level selector l ∈ [0, 1] → level 1 (l ≤ 0.25), 2 (≤ 0.5), 3 (≤ 0.75) or None (off)."""
    try:
        value = float(selector) if not isinstance(selector, (bool, str)) else math.nan
    except (TypeError, ValueError):
        value = math.nan
    if not 0.0 <= value <= 1.0:  # (False for NaN too)
        raise InvalidLevelError(f"a level selector must be a number in [0, 1], got {selector!r}")
    for level, upper in ((1, 0.25), (2, 0.5), (3, 0.75)):
        if value <= upper:
            return level
    return None


def levels_from_selectors(selectors: Mapping[str, float]) -> dict[str, int | None]:
    """Eq. 4 for each task: {task name: l ∈ [0, 1]} → {task name: level or None}, for `A3CQPController(levels=...)`."""
    out = {}
    for name, sel in selectors.items():
        try:
            out[name] = level_from_selector(sel)
        except InvalidLevelError as err:
            raise InvalidLevelError(f"task {name!r}: {err}") from None
    return out


@dataclass(frozen=True)
class Hierarchy:
    """The stack S of eq. 3: which tasks share each strict level (highest priority first) and which are off."""

    levels: tuple[tuple[str, ...], ...]
    """Task names per non-empty level, highest priority first (levels 1 and 3 with 2 empty give two entries;
    ((),) when every task is off: the QP then only regularizes)."""
    off: tuple[str, ...] = ()
    """Deactivated tasks (not in the stack)."""

    @classmethod
    def of(cls, task_names: Sequence[str],
           levels: Mapping[str, int | None] | Sequence[int | None] | None = None) -> "Hierarchy":
        """Validate `levels` against the controller's tasks: a mapping {task name: 1..3 or None}, a sequence in
        task order, or None (every task in level 1: the single weighted QP)."""
        names = list(task_names)
        if levels is None:
            return cls(levels=(tuple(names),))
        if len(set(names)) != len(names):
            raise InvalidLevelError(f"task names must be unique to be given levels, got {names}")
        if isinstance(levels, Mapping):
            unknown = [k for k in levels if k not in names]
            missing = [k for k in names if k not in levels]
            if unknown or missing:
                raise InvalidLevelError(
                    f"levels must name each task once: unknown {unknown}, missing {missing} (tasks: {names}; "
                    f"give each a level 1-{MAX_LEVEL} or None for off)")
            by_name = dict(levels)
        elif isinstance(levels, Sequence) and not isinstance(levels, str):
            if len(levels) != len(names):
                raise InvalidLevelError(f"levels has {len(levels)} entries for {len(names)} tasks {names}")
            by_name = dict(zip(names, levels))
        else:
            raise InvalidLevelError(f"levels must be a mapping task name -> level, a sequence or None, "
                                    f"got {type(levels).__name__}")
        for name, level in by_name.items():
            if level is not None and (isinstance(level, bool) or not isinstance(level, numbers.Integral)
                                      or not 1 <= level <= MAX_LEVEL):
                raise InvalidLevelError(f"task {name!r}: level must be an integer 1-{MAX_LEVEL} or None (off), "
                                        f"got {level!r}")
        stack = tuple(lvl for k in range(1, MAX_LEVEL + 1)
                      if (lvl := tuple(n for n in names if by_name[n] == k)))
        return cls(levels=stack or ((),), off=tuple(n for n in names if by_name[n] is None))

    @property
    def strict(self) -> bool:
        """More than one level: the cascade runs instead of the single weighted QP."""
        return len(self.levels) > 1

    @property
    def is_flat(self) -> bool:
        """Every task active in one level: exactly the single weighted QP of eq. 1."""
        return len(self.levels) == 1 and not self.off

    @property
    def active(self) -> tuple[str, ...]:
        """The tasks in the stack, highest level first."""
        return tuple(n for lvl in self.levels for n in lvl)

    def __str__(self) -> str:
        """The stack in the notation of eq. 3, e.g. "(ik + cartesian_regularizer) / (jc); off: ac, fc"."""
        s = " / ".join("(" + " + ".join(lvl) + ")" for lvl in self.levels)
        return s + (f"; off: {', '.join(self.off)}" if self.off else "")


@dataclass(frozen=True)
class CascadeSolution:
    """Result of `solve_cascade` for a batch [B]."""

    x: torch.Tensor
    """Solution of the last level [B, n]."""
    status: torch.Tensor
    """First non-zero QPStatus over the levels per instance [B] (0: every level solved)."""
    iterations: torch.Tensor
    """QP iterations summed over the levels [B]."""
    solutions: tuple[QPSolution, ...]
    """Each level's QPSolution (in its own variable; the warm starts of the next step)."""


def _null_projector(H: Array, rank_tol: float) -> Array:
    """I − Q Qᵀ [B, n, n] with Q an orthonormal basis of range(H) (symmetric PSD H [B, n, n], numerical rank)."""
    evals, V = torch.linalg.eigh(torch.as_tensor(H))  # (torch's batched eigh: ~1.2x faster than numpy's at B = 64)
    if isinstance(H, np.ndarray):
        evals, V = evals.numpy(), V.numpy()
    cut = rank_tol * evals[:, -1:].clip(0.0, None)
    Vn = V * (evals <= cut)[:, None, :]  # the eigenvectors of the (numerically) zero eigenvalues
    return mm(Vn, Vn.mT)


def _solve_feasible(P: torch.Tensor, c: torch.Tensor, G: torch.Tensor, h: torch.Tensor, warm: QPSolution | None,
                    max_iter: int) -> QPSolution:
    """solve_qp for a QP known to be feasible (z = 0 is): instances it fails on are solved once more cold.

    (Seen: a warm-started batch of 64 that hit MAX_ITER on an instance the cold solve certifies in 5 iterations.)"""
    sol = solve_qp(P, c, G=G, h=h, warm_start=warm, max_iter=max_iter)
    bad = (sol.status != 0).nonzero().flatten()
    if warm is None or bad.numel() == 0:
        return sol
    again = solve_qp(P[bad], c[bad], G=G[bad], h=h[bad], max_iter=max_iter)
    fields = {}
    for f in ("x", "y", "z", "z_lb", "z_ub", "status", "iterations"):
        t = getattr(sol, f).clone()
        t[bad] = getattr(again, f) + (getattr(sol, f)[bad] if f == "iterations" else 0)
        fields[f] = t
    return QPSolution(**fields)


def solve_cascade(costs: Sequence[tuple[torch.Tensor, torch.Tensor]], G: torch.Tensor, h: torch.Tensor,
                  regularization: float, *, warm: Sequence[QPSolution | None] | None = None, max_iter: int = 50,
                  rank_tol: float = RANK_TOL, hand_on: bool = True) -> CascadeSolution:
    """Strict priorities (eq. 2): level k minimises its cost over the optima of levels 1..k−1 within G x ≤ h.

    Args:
        costs: per level, highest first, (P_k [B, n, n], c_k [B, n]) of ½xᵀP_k x + c_kᵀx = ½ Σ_i ‖A_i x − b_i‖²_{W_i}
            + ½ r‖x‖² (+ const), i.e. P_k = H_k + r I with H_k = Σ_i A_iᵀ W_i A_i (what the controller builds).
        G, h: the limits [B, m, n], [B, m], the same at every level.
        regularization: r (the Tikhonov term in every P_k).
        warm: each level's QPSolution of the previous step (or None).
        max_iter: solve_qp's interior-point budget per level.
        rank_tol: see RANK_TOL.
        hand_on: solve_qp's, for level 1 (the only level that can be infeasible; the lower ones keep it on).

    Level 1 is solve_qp(P_1, c_1, G, h). For k > 1 the optima of the levels above are the x with
    A_j x = A_j x_{k−1} (j < k: a strictly convex cost of the residual has one optimal residual), i.e.
    H_{<k} (x − x_{k−1}) = 0 with H_{<k} = Σ_{j<k} H_j. Instead of equality rows (stacked rows of the levels above
    are often dependent, which the solver would have to detect) x = x_{k−1} + N z with N the orthogonal projector
    on the null space of H_{<k} (eigendecomposition with a rank tolerance), so that every level has the same n
    variables and m rows for all robots:
        min_z ½ zᵀ (N H_k N + r N + ρ (I − N)) z + (N (P_k x_{k−1} + c_k))ᵀ z   s.t.   G N z ≤ max(h − G x_{k−1}, 0).
    (ρ zᵀ(I − N)z, ρ = P_k's mean diagonal, makes the Hessian definite; it only sets the part of z that N removes
    to 0.)
    z = 0 is feasible (x_{k−1} satisfies the limits), so a lower level cannot be infeasible; the max(·, 0) keeps
    x_{k−1}'s solver-tolerance violations from making it so. Rows G N that vanish are made inert. A lower level
    the warm-started solver fails on is solved once more cold (its failure cannot be infeasibility).
    CPU tensors are handled as numpy views in between the solves (small ops: see control/arrays.py).
    """
    if not costs:
        raise InvalidLevelError("solve_cascade needs at least one level")
    warm = list(warm) if warm is not None else []
    warm += [None] * (len(costs) - len(warm))
    on_cpu = G.device.type == "cpu"
    arr = (lambda t: t.numpy()) if on_cpu else (lambda t: t)  # noqa: E731
    ten = torch.as_tensor
    sols: list[QPSolution] = []
    x = status = iterations = H_above = None
    G_, h_ = arr(G), arr(h)
    for k, (P, c) in enumerate(costs):
        w = warm[k] if warm[k] is not None and warm[k].z.shape == h.shape else None
        if k == 0:
            sol = solve_qp(P, c, G=G, h=h, warm_start=w, max_iter=max_iter, hand_on=hand_on)
            x, status, iterations = arr(sol.x), sol.status, sol.iterations
        else:
            P_, c_ = arr(P), arr(c)
            eye = const(torch.eye(P.shape[-1], dtype=P.dtype), P_)
            H_prev = arr(costs[k - 1][0]) - regularization * eye
            H_above = H_prev if H_above is None else H_above + H_prev
            N = _null_projector(H_above, rank_tol)  # (B, n, n)
            Hz = mm(mm(N, P_ - regularization * eye), N)
            # on range(I − N) any definite weight sets z's part there to 0; P_k's mean diagonal ρ rather than r keeps
            # the Hessian as well conditioned as P_k (with r = 1e-6 the solver failed on degenerate instances)
            rho = P_.diagonal(0, -2, -1).mean(-1)[:, None, None]
            Pz = 0.5 * (Hz + Hz.mT) + regularization * N + rho * (eye - N)
            cz = mv(N, mv(P_, x) + c_)
            Gz = mm(G_, N)
            keep = ((Gz * Gz).sum(-1) > _ROW_TOL ** 2 * (G_ * G_).sum(-1))[..., None]
            Gz = Gz * keep
            hz = (h_ - mv(G_, x)).clip(0.0, None)
            sol = _solve_feasible(ten(Pz), ten(cz), ten(Gz), ten(hz), w, max_iter)
            x = x + mv(N, arr(sol.x))
            status = torch.where(status != 0, status, sol.status)
            iterations = iterations + sol.iterations
        sols.append(sol)
    return CascadeSolution(x=ten(x), status=status, iterations=iterations, solutions=tuple(sols))
