"""Batched dense QP solver in pure torch, differentiable through the KKT conditions.

Problem, for each element of a batch [B] with the same sizes::

    minimise ½ xᵀ P x + qᵀ x   subject to   A x = b,   G x ≤ h,   lb ≤ x ≤ ub.

Algorithm (why this one)
------------------------
The controller solves one small QP (n ≈ 13, m ≈ 30-40 rows) per robot every millisecond, with a
solution from the previous millisecond at hand, and training solves thousands at once.  In eager
torch every op costs a few µs whatever its size, so at B = 1 the *number of ops* decides latency;
at B = 1024 the passes over the [B, m, n] constraint data and the batched factorisations decide
throughput.  Measured here: an interior-point (IPM) iteration is ~150 torch calls (0.5-0.9 ms at
B = 1 on the shared 2-core box) and forming P + Gᵀ D G costs ~1 ms at B = 1024; a cold IPM needs
7-20 iterations, while an active-set iteration is ~40 calls.  So the
solver works in two stages, each vectorised over the batch:

1. **Primal-dual active set (PDAS: semismooth Newton on min(z, h − Gx) = 0)**, from the warm
   start's active set (or the empty set).  Each iteration solves the equality-constrained QP of
   the working set W (Ax = b, G_W x = h_W) exactly:
   - B ≤ 32: one batched LU of the masked KKT matrix (fewest ops, lowest latency);
   - B > 32: Cholesky of P once per solve, then the Schur complement on the *gathered* working
     rows only (k = max |W|, typically 0-5 of 30 rows), O(n²k) per iteration;
   - fallback (singular KKT: dependent active rows, P singular on their null space): a proximal
     augmented Lagrangian on the Cholesky factor of P + C_Wᵀ ρ C_W + δI, which stays definite.
   A candidate is accepted only when *certified* optimal a posteriori (KKT residual of the
   working set, primal feasibility of every row and non-negative multipliers, all within tol), so
   this stage never returns a wrong answer.  Warm-started in the control loop the active set
   rarely changes and one PDAS iteration solves the QP; cold, W = ∅ already solves every instance
   whose unconstrained optimum is feasible; the controller-like test family needs 1-4 iterations,
   heavily constrained instances (5-10 active rows) 5-15 or the IPM.
2. **Mehrotra predictor-corrector IPM** for the instances the active-set stage did not certify
   within `active_set_iter` iterations (15 for B ≤ 32, 10 above) (cycling, many active-set changes, infeasible or unbounded
   problems).  It factors P + Gᵀ(z/s)G (+ρAᵀA with a p × p Schur complement for equalities) by
   batched Cholesky on unit-norm rows, detects primal infeasibility (Farkas certificate from the
   duals) and unboundedness (a recession direction from the steps), drops finished instances
   from the working batch, and its strictly complementary active set (z > s) seeds a final PDAS
   "polish" that returns the exact solution of that active set.

Small CPU batches (dispatch)
----------------------------
At B = 1 the stages above are op-bound: a warm-started solve is ~60 torch calls (180-400 µs),
slower than proxsuite.torch, and a cold heavily constrained one pays for IPM iterations of ~150
calls each.  So small CPU batches go through `small_batch.py` instead: per instance in numpy
(~1 µs per call on these sizes instead of ~4-7 µs per torch op), a Goldfarb-Idnani dual active
set warm-started from the previous working set (one KKT solve in the control loop, 10-18 on
heavily constrained instances, no IPM), with the same certificate; what it does not certify
(singular P or rows, infeasible, unbounded, NaN) goes to the batched stages above, so answers and
statuses are the batched path's.  The backward of those batches solves the adjoint system per
instance in numpy too (same equations; the torch adjoint if a system is singular).  Both the
active set (cold and warm) and the adjoint also exist in C (`native/gi_qp.c`, compiled on first
use, one ctypes call per batch, same decisions and certificates; the numpy code is the fallback
and the reference), which takes the numpy call overhead out of B = 1.  The Python
loop grows with B while the batched torch path is nearly flat, so the route is chosen by batch
size (CPU only; a CUDA batch always takes the batched path):

- B ≤ `SMALL_BATCH_MAX_WARM` (8) with a warm start, B ≤ `SMALL_BATCH_MAX` (16) without: numpy.
- Measured crossovers (µs per QP, numpy / batched torch, 13 variables, 30 rows, 1 thread, the
  shared box under load, so ratios matter more than values): warm forward B = 8: 128 / 130,
  B = 16: 109 / 88; cold forward B = 16: 187 / 251, B = 32: 171 / 195, B = 64: 158 / 89 (spread
  0.35, where the batched path needs its IPM: numpy wins up to B ≈ 64); backward alone B = 16:
  76 / 123.  At B = 1: warm 407 / 736, cold 712 / 1318, cold heavily constrained 1209 / 3639.
  (Those numbers predate the range-space cold start of `small_batch.py`; with it and the leaner
  wrapper, B = 1 against proxsuite.torch, medians of 3 `bench/qp.py` runs: default instances
  cold 1.24× forward / 1.16× forward+backward, warm 2.24× / 1.45×; heavily constrained (spread
  0.35) cold 0.97× / 1.00×, warm 2.80× / 1.66×.  With the C routines, same protocol, old path
  (A3CQP_NATIVE_QP=0) and new back to back: default cold 1.24× → 2.30× forward, 1.22× → 1.74×
  forward+backward, warm 2.09× → 2.55× / 1.46× → 1.81×; heavily constrained cold 1.02× → 2.55× /
  1.14× → 2.05×, warm 2.66× → 3.65× / 1.57× → 2.15×.  Against proxsuite's parallel BatchQP
  (forward only) cold 0.58× → 1.15× (default), 0.56× → 1.53× (heavy).)

Code: `kkt.py` (the three working-set solves), `active_set.py` (stage 1), `interior_point.py`
(stage 2), `small_batch.py` (the small-batch route), this file (assembly, polish, autograd,
dispatch, `solve_qp`).

Infinite bounds and right-hand sides become inert rows (0·x ≤ 1), and a failed instance never
produces NaN: x is the last finite iterate and `status` says what happened.

Backward: implicit differentiation of the KKT system at the solution (as OptNet/qpth), with the
active set read from the duals and slacks (z > h − Gx).  The adjoint system has the same structure
as a PDAS step and is solved by the same LU / Schur / augmented-Lagrangian routines; it gives the
gradients with respect to P, q, A, b, G, h, lb, ub in closed form.  Nothing is unrolled.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from a3cqp_rl.qp.active_set import active_set_stage, residual_scales
from a3cqp_rl.qp.exceptions import QPShapeError
from a3cqp_rl.qp.interior_point import interior_point
from a3cqp_rl.qp.kkt import LU_MAX_BATCH, eq_solve_alm, kkt_lu, kkt_schur, mv
from a3cqp_rl.qp import native, small_batch
from a3cqp_rl.qp.small_batch import EXHAUSTED, SINGULAR, active_set_small, adjoint_small, gradients_native
from a3cqp_rl.qp.status import QPStatus

__all__ = ["QPStatus", "QPSolution", "solve_qp", "SMALL_BATCH_MAX", "SMALL_BATCH_MAX_WARM"]

SMALL_BATCH_MAX = 16
"""Largest CPU batch solved (and differentiated) by the numpy per-instance path, `small_batch.py`
(measured crossover: see the module docstring)."""
SMALL_BATCH_MAX_WARM = 8
"""Same, for warm-started solves: both paths then certify in one iteration, which the batched
path amortises over the batch sooner."""
NATIVE_BATCH_MAX = 4096
"""With the C routine loaded, CPU batches up to this size take the per-instance path as well: one C call
loops over the batch, which beats the batched torch path at every size measured (µs per QP, C / batched
torch, 1 thread: B = 64 heavily constrained cold 13.5 / 415; B = 1024 heavily constrained cold 12.4 / 178,
forward+backward 17.6 / 171; B = 1024 default cold 6.4 / 8.1).  Above `SMALL_BATCH_MAX` what C does
not certify goes straight to the batched path (a numpy retry per instance would not scale)."""
SMALL_MAX_STEPS = 100
"""Step budget of the numpy dual active set (one KKT solve per step) before the interior point.
Goldfarb-Idnani is finite (each step adds or drops a row); heavily constrained controller-sized
instances need 10-30, so the budget only stops numerical cycling."""


@dataclass
class QPSolution:
    """Solution of a batch of QPs; duals follow L = ½xᵀPx + qᵀx + yᵀ(Ax − b) + zᵀ(Gx − h) + ...."""

    x: Tensor
    """Primal solution [B, n]."""
    y: Tensor
    """Multipliers of A x = b [B, p]."""
    z: Tensor
    """Multipliers (≥ 0) of G x ≤ h [B, m]."""
    z_lb: Tensor
    """Multipliers (≥ 0) of lb ≤ x [B, n] (zero where lb is absent or infinite)."""
    z_ub: Tensor
    """Multipliers (≥ 0) of x ≤ ub [B, n] (zero where ub is absent or infinite)."""
    status: Tensor
    """QPStatus code per instance [B] (int64)."""
    iterations: Tensor
    """Number of KKT factorisations (active-set + interior-point iterations) per instance [B]."""

    @property
    def solved(self) -> Tensor:
        """Boolean mask [B] of instances with status SOLVED."""
        return self.status == QPStatus.SOLVED


# ----------------------------------------------------------------------------------------------
# Problem assembly
# ----------------------------------------------------------------------------------------------


def _batched(t: Tensor | None, name: str, ndim: int, batch: int, dtype: torch.dtype) -> Tensor | None:
    """Check dims of a QP argument and expand an unbatched one to the batch size."""
    if t is None:
        return None
    if t.dtype != dtype:
        raise QPShapeError(f"{name} has dtype {t.dtype}, expected {dtype} (the dtype of q)")
    if t.dim() == ndim - 1:
        t = t.unsqueeze(0)
    if t.dim() != ndim:
        raise QPShapeError(f"{name} must have {ndim} dims [B, ...], got shape {tuple(t.shape)}")
    if t.shape[0] == 1 and batch > 1:
        t = t.expand(batch, *t.shape[1:])
    elif t.shape[0] != batch:
        raise QPShapeError(f"{name} has batch size {t.shape[0]}, expected {batch}")
    return t


_EMPTY_EQ: dict[tuple, tuple[Tensor, Tensor]] = {}


def _no_equalities(batch: int, n: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """Empty A [B, 0, n] and b [B, 0], cached per shape/dtype/device: two allocations are ~5 µs of
    the B = 1 budget, and a tensor with no elements cannot be changed by whoever holds it."""
    key = (batch, n, like.dtype, like.device)
    eq = _EMPTY_EQ.get(key)
    if eq is None:
        if len(_EMPTY_EQ) > 64:
            _EMPTY_EQ.clear()
        eq = _EMPTY_EQ[key] = (like.new_zeros(batch, 0, n), like.new_zeros(batch, 0))
    return eq


def _stack_inequalities(
    G: Tensor | None, h: Tensor | None, lb: Tensor | None, ub: Tensor | None, batch: int, n: int, like: Tensor
) -> tuple[Tensor, Tensor, int, bool, bool]:
    """Stack G x ≤ h, −x ≤ −lb, x ≤ ub into one (G_all, h_all), with infinite rows made inert."""
    if G is not None and lb is None and ub is None:  # the controller's case: nothing to stack
        return *_inert_infinite_rows(G, h, like), G.shape[1], False, False
    rows_G, rows_h = [], []
    m = 0
    if G is not None:
        rows_G.append(G)
        rows_h.append(h)
        m = G.shape[1]
    has_lb, has_ub = lb is not None, ub is not None
    if has_lb or has_ub:
        eye = torch.eye(n, dtype=like.dtype, device=like.device).expand(batch, n, n)
    if has_lb:
        rows_G.append(-eye)
        rows_h.append(-lb)
    if has_ub:
        rows_G.append(eye)
        rows_h.append(ub)
    if not rows_G:
        empty = like.new_zeros(batch, 0, n)
        return empty, like.new_zeros(batch, 0), 0, False, False
    G_all = torch.cat(rows_G, 1) if len(rows_G) > 1 else rows_G[0]
    h_all = torch.cat(rows_h, 1) if len(rows_h) > 1 else rows_h[0]
    return *_inert_infinite_rows(G_all, h_all, like), m, has_lb, has_ub


def _inert_infinite_rows(G: Tensor, h: Tensor, like: Tensor) -> tuple[Tensor, Tensor]:
    """Rows with an infinite right-hand side replaced by 0·x ≤ 1.

    An infinite right-hand side is no constraint; 0·x ≤ 1 is always satisfied with slack 1 and a
    zero multiplier, so every instance keeps the same row count."""
    if h.is_cpu:
        # Three torch calls are ~10 µs of the B = 1 budget (~25 at B = 64): test in numpy.  A finite
        # sum proves every entry finite (a non-finite one, or an overflow, takes the exact test below).
        if math.isfinite(_np64(h).sum()):
            return G, h
    finite = torch.isfinite(h)
    if bool(finite.all()):
        return G, h
    G = torch.where(finite.unsqueeze(-1), G, torch.zeros((), dtype=like.dtype))
    h = torch.where(finite, h, torch.ones((), dtype=like.dtype))
    return G, h


# ----------------------------------------------------------------------------------------------
# Forward driver and autograd
# ----------------------------------------------------------------------------------------------


_IPM_POLISH_TOL = 1e-6
"""Complementarity at which the interior point hands its active set to the exact polish."""


def _ipm_polished(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, sp: Tensor, sd: Tensor,
    tol_ipm: float, tol: float, max_iter: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Interior point to tol_ipm, then an active-set polish to tol; returns x, y, z, status, iterations, polished."""
    nb, n = q.shape
    m = G.shape[1]
    # Unit-norm rows for the interior point: one tolerance fits all rows and its Farkas test is
    # scale-free; multipliers are scaled back below.
    nA = A.norm(dim=-1).clamp_min(1e-30)
    nG = G.norm(dim=-1)
    nG = torch.where(nG > 0, nG, torch.ones((), dtype=q.dtype))
    Gs, hs = (G / nG.unsqueeze(-1), h / nG) if m else (q.new_zeros(nb, 1, n), q.new_ones(nb, 1))
    xi, yi, zi, si, ii = interior_point(P, q, A / nA.unsqueeze(-1), b / nA, Gs, hs, tol_ipm, max_iter)
    yi = yi / nA
    # Active set decided in the normalised rows, where multipliers and slacks are comparable.
    act_ipm = zi[:, :m] > (hs - mv(Gs, xi))[:, :m]
    zi = zi[:, :m] / nG
    polished = torch.zeros(nb, dtype=torch.bool, device=q.device)
    good = (si == QPStatus.SOLVED).nonzero().squeeze(-1)
    if good.numel():
        # Polish: the IPM's strictly complementary active set (z > s) seeds an active-set solve,
        # which returns the exact solution of that active set and multipliers that are zero on
        # inactive rows (an IPM stopped at μ leaves O(√μ) errors on degenerate rows).
        z_act = torch.where(act_ipm, zi, torch.zeros((), dtype=q.dtype)) if m else zi
        sub = [t.index_select(0, good) for t in (P, q, A, b, G, h, z_act, sp, sd)]
        xp, yp, zp, okp, itp = active_set_stage(*sub, tol, 2)
        sel = good[okp]
        xi[sel], zi[sel], yi[sel], polished[sel] = xp[okp], zp[okp], yp[okp], True
        ii[good] = ii[good] + itp.clamp(max=2)
    return xi, yi, zi, si, ii, polished


def _solve_canonical(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, z_warm: Tensor | None,
    tol: float, max_iter: int, active_set_iter: int | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, tuple[np.ndarray, ...] | None]:
    """Solve the canonical batch (no autograd); returns x, y, z, status, iterations and, on the
    small-batch path, the float64 numpy (P symmetrised, A, G, h) for the backward (else None)."""
    if _use_small_path(q, SMALL_BATCH_MAX_WARM if z_warm is not None else SMALL_BATCH_MAX):
        return _solve_small(P, q, A, b, G, h, z_warm, tol, max_iter, active_set_iter)
    if _use_native_path(q):
        return _solve_small(P, q, A, b, G, h, z_warm, tol, max_iter, active_set_iter, numpy_retry=False)
    return (*_solve_batched(P, q, A, b, G, h, z_warm, tol, max_iter, active_set_iter), None)


def _use_native_path(x: Tensor) -> bool:
    """Whether a batch above the numpy sizes still takes the per-instance path (the C routine is loaded)."""
    return _use_small_path(x, NATIVE_BATCH_MAX) and small_batch.NATIVE and native.load() is not None


def _use_small_path(q: Tensor, limit: int | None = None) -> bool:
    """Whether this batch goes through the numpy per-instance path (at most `limit` instances, on CPU)."""
    return q.shape[0] <= (SMALL_BATCH_MAX if limit is None else limit) and q.is_cpu


def _np64(t: Tensor) -> np.ndarray:
    """Float64 numpy view (zero-copy for float64 CPU tensors, expanded ones included) of a tensor."""
    if t.requires_grad:  # (detach costs ~2 µs: only when needed)
        t = t.detach()
    return (t if t.dtype == torch.float64 else t.double()).numpy()


def _from_np(v: np.ndarray, dtype: torch.dtype) -> Tensor:
    """Torch tensor of a float64 numpy result, in the caller's dtype (no copy for float64)."""
    t = torch.from_numpy(v)
    return t if dtype == torch.float64 else t.to(dtype)


def _solve_small(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, z_warm: Tensor | None,
    tol: float, max_iter: int, active_set_iter: int | None, numpy_retry: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, tuple[np.ndarray, ...]]:
    """Small-batch route: numpy active set per instance, the batched torch path for what it leaves.

    `numpy_retry=False`: what the C routine leaves goes to the batched path without the numpy retry.

    The returned cache is (P symmetrised, A, G, h) in float64 numpy, plus (x, y, z) when every
    instance was certified here (all SOLVED)."""
    B = q.shape[0]
    Pn = _np64(P)
    Ps, An, Gn, hn = 0.5 * (Pn + Pn.transpose(0, 2, 1)), _np64(A), _np64(G), _np64(h)
    cache = (Ps, An, Gn, hn)
    xn, yn, zn, outcome, itn = active_set_small(
        Ps, _np64(q), An, _np64(b), Gn, hn,
        _np64(z_warm) if z_warm is not None else None, tol, SMALL_MAX_STEPS if active_set_iter is None else active_set_iter,
        numpy_retry=numpy_retry,
    )
    x, y, z = (_from_np(v, q.dtype) for v in (xn, yn, zn))
    iters = torch.from_numpy(itn)
    status = torch.from_numpy(np.zeros(B, dtype=np.int64))  # QPStatus.SOLVED; from numpy: ~3x cheaper
    if not outcome[outcome.argmax()]:  # every instance CERTIFIED (= 0); argmax + index ~5x cheaper than any()
        # All solved by numpy: the backward can use these float64 results as they are.
        return x, y, z, status, iters, (*cache, xn, yn, zn)
    # Singular working-set systems get the torch active set (its augmented Lagrangian copes with
    # dependent rows); instances that used up the iterations go straight to the interior point.
    for code, as_iter in ((SINGULAR, active_set_iter), (EXHAUSTED, 0)):
        sel = np.flatnonzero(outcome == code)
        if sel.size == 0:
            continue
        idx = torch.from_numpy(sel)
        sub = [t.index_select(0, idx) for t in (P, q, A, b, G, h)]
        zw = z_warm.index_select(0, idx) if z_warm is not None else None
        xs, ys, zs, ss, its = _solve_batched(*sub, zw, tol, max_iter, as_iter)
        x[idx], y[idx], z[idx], status[idx] = xs, ys, zs, ss
        iters[idx] = its + (iters[idx] if code == EXHAUSTED else 0)
    return x, y, z, status, iters, cache


def _solve_batched(
    P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor, z_warm: Tensor | None,
    tol: float, max_iter: int, active_set_iter: int | None,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Batched torch route: active-set stage on the whole batch, interior point for what it leaves."""
    B, n = q.shape
    if active_set_iter is None:
        active_set_iter = 15 if B <= LU_MAX_BATCH else 10
    p, m = A.shape[1], G.shape[1]
    P = 0.5 * (P + P.mT)
    sp, sd = residual_scales(q, b, h)
    z0 = z_warm if z_warm is not None else q.new_zeros(B, m)
    x, y, z, ok, iters = active_set_stage(P, q, A, b, G, h, z0, sp, sd, tol, active_set_iter)
    if bool(ok.all()):
        return x, y, z, torch.zeros(B, dtype=torch.long, device=q.device), iters

    bad = ok.logical_not().nonzero().squeeze(-1)
    status = torch.zeros(B, dtype=torch.long, device=q.device)
    sub = [t.index_select(0, bad) for t in (P, q, A, b, G, h, sp, sd)]
    # The IPM only has to find the active set: stopped at a looser μ, its strictly complementary
    # set seeds the polish, which is exact.  Only where that polish fails (degenerate or weakly
    # active rows) is the IPM rerun to the full tolerance.
    tol_ipm = max(tol, _IPM_POLISH_TOL)
    xi, yi, zi, si, ii, pol = _ipm_polished(*sub, tol_ipm, tol, max_iter)
    redo = ((si == QPStatus.SOLVED) & ~pol).nonzero().squeeze(-1) if tol_ipm > tol else pol[:0].nonzero().squeeze(-1)
    if redo.numel():
        xr, yr, zr, sr, ir, _ = _ipm_polished(*(t.index_select(0, redo) for t in sub), tol, tol, max_iter)
        xi[redo], yi[redo], zi[redo], si[redo], ii[redo] = xr, yr, zr, sr, ii[redo] + ir
    x[bad], y[bad], z[bad], status[bad], iters[bad] = xi, yi, zi, si, iters[bad] + ii
    # Never hand NaN/inf to the caller: a failed instance keeps a finite (if meaningless) x.
    x = torch.nan_to_num(x, nan=0.0, posinf=0.0, neginf=0.0)
    y = torch.nan_to_num(y, nan=0.0, posinf=0.0, neginf=0.0)
    z = torch.nan_to_num(z.clamp_min(0.0), nan=0.0, posinf=0.0, neginf=0.0)
    return x, y, z, status, iters


def _adjoint_direct(P: Tensor, gx: Tensor, C: Tensor, zr: Tensor, mask: Tensor) -> tuple[Tensor, Tensor, Tensor | None]:
    """Direct solve of the adjoint KKT system (LU for small batches, Schur on the working rows for large)."""
    if gx.shape[0] <= LU_MAX_BATCH:
        return kkt_lu(P, -gx, C, zr, mask)
    L, info = torch.linalg.cholesky_ex(P)
    if not bool((info == 0).all()):
        return gx, zr, None
    x_u = torch.cholesky_solve(gx.unsqueeze(-1), L).squeeze(-1)
    return kkt_schur(L, x_u, P, -gx, C, zr, mask)


def _backward_small(
    need: tuple[bool, ...], P: Tensor, A: Tensor, G: Tensor, h: Tensor, x: Tensor, y: Tensor, z: Tensor,
    status: Tensor, gx: Tensor, cache: tuple[np.ndarray, ...] | None = None, numpy_fallback: bool = True,
) -> tuple[Tensor | None, ...] | None:
    """Gradients (P, q, A, b, G, h) by the numpy adjoint (small CPU batches); None if a system is singular.

    `numpy_fallback=False`: None (the batched torch backward) where the C adjoint declines, no numpy loop.

    `cache`: the forward's float64 numpy (P symmetrised, A, G, h[, x, y, z]), saving their conversions."""
    if cache is None:
        Pn = _np64(P)
        cache = (0.5 * (Pn + Pn.transpose(0, 2, 1)), _np64(A), _np64(G), _np64(h))
    gxn = _np64(gx)
    if len(cache) == 7:  # every instance SOLVED in numpy: its float64 results
        Ps, An, Gn, hn, xn, yn, zn = cache
    else:
        (Ps, An, Gn, hn), (xn, yn, zn) = cache[:4], (_np64(x), _np64(y), _np64(z))
        # Gradients only flow through x of solved instances (as in the torch backward).
        st = status.numpy()
        if st.any():  # some instance not SOLVED (= 0; an IntEnum operand would take numpy's object path)
            gxn = gxn * (st == 0)[:, None]
    dt = x.dtype

    def out(v: np.ndarray) -> Tensor:
        return _from_np(v, dt)

    grads = gradients_native(Ps, An, Gn, hn, xn, yn, zn, gxn)  # adjoint and closed forms in one C call
    if grads is not None:
        return tuple(out(g) if need[k] or k % 2 else None for k, g in enumerate(grads))
    if not numpy_fallback:
        return None
    adj = adjoint_small(Ps, An, Gn, hn, xn, zn, gxn)
    if adj is None:
        return None
    wx, wy, wz, active = adj

    # Same closed forms as the torch backward: −½(x wxᵀ + wx xᵀ), −(ν wxᵀ + wν xᵀ).
    gP = gA = gG = None
    if need[0]:
        xw = xn[:, :, None] * wx[:, None, :]
        xw += xw.transpose(0, 2, 1)
        xw *= -0.5
        gP = out(xw)
    if need[2]:
        gA = out(-(yn[:, :, None] * wx[:, None, :] + wy[:, :, None] * xn[:, None, :]))
    if need[4]:
        gGn = (zn * active)[:, :, None] * wx[:, None, :]
        gGn += wz[:, :, None] * xn[:, None, :]
        gG = out(np.negative(gGn, out=gGn))
    wx = np.negative(wx, out=wx)
    return gP, out(wx), gA, out(wy), gG, out(wz)


class _QPFunction(torch.autograd.Function):
    """x*(P, q, A, b, G, h) with a backward by implicit differentiation of the KKT conditions."""

    @staticmethod
    def forward(ctx, P, q, A, b, G, h, z_warm, tol, max_iter, active_set_iter):  # type: ignore[override]
        # Gradients of y, z, status, iterations are never used: without materialisation autograd
        # passes None for them instead of allocating zeros (~10 µs at B = 1).
        ctx.set_materialize_grads(False)
        x, y, z, status, iters, ctx.np_cache = _solve_canonical(P, q, A, b, G, h, z_warm, tol, max_iter, active_set_iter)
        ctx.save_for_backward(P, A, G, h, x, y, z, status)
        ctx.mark_non_differentiable(status, iters)
        return x, y, z, status, iters

    @staticmethod
    def backward(ctx, gx, gy, gz, _gs, _gi):  # type: ignore[override]
        P, A, G, h, x, y, z, status = ctx.saved_tensors
        p, m = A.shape[1], G.shape[1]
        if gx is None:
            gx = torch.zeros_like(x)
        small = _use_small_path(x)
        if small or (ctx.np_cache is not None and _use_native_path(x)):
            grads = _backward_small(ctx.needs_input_grad, P, A, G, h, x, y, z, status, gx, ctx.np_cache,
                                    numpy_fallback=small)
            if grads is not None:
                return (*grads, None, None, None, None)
        # Gradients only flow through x (duals are outputs for information and warm starts).
        ok = (status == QPStatus.SOLVED).unsqueeze(-1)
        gx = torch.where(ok, gx, torch.zeros((), dtype=gx.dtype))
        Ps = 0.5 * (P + P.mT)
        slack = (h - mv(G, x)).clamp_min(0.0)
        active = z > slack  # strictly complementary part of the active set
        C = torch.cat([A, G], 1) if p else G
        mask = torch.cat([torch.ones_like(y, dtype=torch.bool), active], 1) if p else active
        # Adjoint: [[P, C_Wᵀ], [C_W, 0]] [wx; wν] = [gx; 0], i.e. min ½wᵀPw − gxᵀw s.t. C_W w = 0.
        zr = torch.zeros_like(C[..., 0])
        tol_w = 1e-12 * (1.0 + float(gx.abs().amax()))
        wx, wnu, res = _adjoint_direct(Ps, gx, C, zr, mask)
        if res is None or not bool((res <= tol_w * (1.0 + wnu.abs().amax(-1))).all()):
            # Singular KKT (dependent active rows, P singular on their null space): the augmented
            # Lagrangian is exact in the limit and stays well posed.
            wx, wnu, _, _ = eq_solve_alm(Ps, -gx, C, zr, mask, zr, torch.zeros_like(x), 0.1 * tol_w)
        wy, wz = wnu[:, :p], wnu[:, p:]
        nu = torch.cat([y, z * active], 1) if p else z * active
        # Sums of two outer products as one bmm with inner dimension 2: a single pass over the
        # [B, r, n] output instead of four.
        need = ctx.needs_input_grad
        u = torch.stack([wx, x], -2)  # (B, 2, n)
        gP = (torch.stack([x, wx], -1) @ u).mul_(-0.5) if need[0] else None  # −½(x wxᵀ + wx xᵀ)
        gA = gG = None
        if need[2] or need[4]:
            gC = (torch.stack([nu, wnu], -1) @ u).neg_()  # −(ν wxᵀ + wν xᵀ), (B, r, n)
            gA, gG = gC[:, :p], gC[:, p:]
        return gP, -wx, gA, wy, gG, wz, None, None, None, None


def solve_qp(
    P: Tensor,
    q: Tensor,
    A: Tensor | None = None,
    b: Tensor | None = None,
    G: Tensor | None = None,
    h: Tensor | None = None,
    lb: Tensor | None = None,
    ub: Tensor | None = None,
    *,
    warm_start: QPSolution | None = None,
    tol: float | None = None,
    max_iter: int = 50,
    active_set_iter: int | None = None,
) -> QPSolution:
    """Solve a batch of QPs min ½xᵀPx + qᵀx s.t. Ax = b, Gx ≤ h, lb ≤ x ≤ ub (differentiable).

    Args:
        P: Hessian [B, n, n] (symmetrised internally), positive semi-definite.
        q: linear cost [B, n]; its dtype and device are the solver's.
        A, b: equality rows [B, p, n] and right-hand side [B, p] (both or neither).
        G, h: inequality rows [B, m, n] and right-hand side [B, m]; entries of h may be +inf.
        lb, ub: bounds on x [B, n]; entries may be ∓inf (no bound).
        warm_start: a previous QPSolution of same-sized problems; its multipliers seed the active set.
        tol: absolute tolerance on residuals and complementarity, relative to 1 + |data|;
            default 1e-9 in float64, 1e-5 in float32.
        max_iter: interior-point iteration budget for instances the active-set stage leaves.
        active_set_iter: primal-dual active-set iterations tried before the interior point; default
            15 for B ≤ 32 (an active-set iteration costs ~1/3 of an interior-point one there) and
            10 above (measured best on heavily constrained batches).  On the small-batch CPU path
            (see the module docstring) it is the dual active set's budget of KKT solves instead,
            default `SMALL_MAX_STEPS` (100).

    Any argument may also be given unbatched (without the leading B) to share it across the batch.
    Gradients flow to every tensor argument through x (implicit differentiation of the KKT system).
    """
    if q.dim() not in (1, 2):
        raise QPShapeError(f"q must be [B, n] or [n], got shape {tuple(q.shape)}")
    dtype = q.dtype
    if not dtype.is_floating_point:
        raise QPShapeError(f"q must be a floating tensor, got {dtype}")
    lead = [t.shape[0] for t, k in ((P, 3), (q, 2), (A, 3), (b, 2), (G, 3), (h, 2), (lb, 2), (ub, 2)) if t is not None and t.dim() == k]
    batch = max(lead) if lead else 1
    P = _batched(P, "P", 3, batch, dtype)
    q = _batched(q, "q", 2, batch, dtype)
    n = q.shape[1]
    if P.shape[1:] != (n, n):
        raise QPShapeError(f"P must be [B, {n}, {n}], got {tuple(P.shape)}")
    if (A is None) != (b is None) or (G is None) != (h is None):
        raise QPShapeError("A and b (and G and h) must be given together")
    A, b, G, h = (_batched(t, nm, nd, batch, dtype) for t, nm, nd in ((A, "A", 3), (b, "b", 2), (G, "G", 3), (h, "h", 2)))
    lb, ub = _batched(lb, "lb", 2, batch, dtype), _batched(ub, "ub", 2, batch, dtype)
    for t, nm in ((A, "A"), (G, "G")):
        if t is not None and t.shape[2] != n:
            raise QPShapeError(f"{nm} must have {n} columns, got {tuple(t.shape)}")
    if A is not None and b.shape[1] != A.shape[1]:
        raise QPShapeError(f"b must be [B, {A.shape[1]}], got {tuple(b.shape)}")
    if G is not None and h.shape[1] != G.shape[1]:
        raise QPShapeError(f"h must be [B, {G.shape[1]}], got {tuple(h.shape)}")
    for t, nm in ((lb, "lb"), (ub, "ub")):
        if t is not None and t.shape[1] != n:
            raise QPShapeError(f"{nm} must be [B, {n}], got {tuple(t.shape)}")
    if A is None:
        A, b = _no_equalities(batch, n, q)
    if tol is None:
        tol = 1e-9 if dtype == torch.float64 else 1e-5

    G_all, h_all, m, has_lb, has_ub = _stack_inequalities(G, h, lb, ub, batch, n, q)
    z_warm = None
    if warm_start is not None:
        parts = [warm_start.z] if G is not None else []
        parts += [warm_start.z_lb] if has_lb else []
        parts += [warm_start.z_ub] if has_ub else []
        if parts:
            z_warm = (torch.cat(parts, -1) if len(parts) > 1 else parts[0]).detach()
            if z_warm.dtype != dtype:
                z_warm = z_warm.to(dtype)
            if z_warm.shape != h_all.shape:
                raise QPShapeError(f"warm_start duals have shape {tuple(z_warm.shape)}, expected {tuple(h_all.shape)}")

    solver_args = (z_warm, float(tol), int(max_iter), None if active_set_iter is None else int(active_set_iter))
    if torch.is_grad_enabled() and any(t.requires_grad for t in (P, q, A, b, G_all, h_all)):
        x, y, z_all, status, iters = _QPFunction.apply(P, q, A, b, G_all, h_all, *solver_args)
    else:
        x, y, z_all, status, iters, _ = _solve_canonical(P, q, A, b, G_all, h_all, *solver_args)
    zero = q.new_zeros(batch, n)
    z = z_all if not (has_lb or has_ub) else z_all[:, :m]  # a slice is ~5 µs of the B = 1 budget
    z_lb = z_all[:, m : m + n] if has_lb else zero
    z_ub = z_all[:, m + n * has_lb :] if has_ub else zero
    return QPSolution(x=x, y=y, z=z, z_lb=z_lb, z_ub=z_ub, status=status, iterations=iters)
