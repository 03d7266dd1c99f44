"""`qp_vjp`: gradients of a solved batch without an autograd graph (the C route's vector-Jacobian product).

    sol = solve_qp(P, q, G=G, h=h)          # no argument requires grad: the C route
    g = qp_vjp(sol, gx)                     # g.P, g.q, g.G, g.h: gradients of Σ gx·x* in the arguments' shapes

Why: at controller size a solve costs a few µs, while an autograd graph around it (a custom Function, its
saved tensors, the engine's backward pass) costs ~30 µs whatever the function does (measured 2026-11-24 with an
identity in place of the QP).  Callers that know the cotangent of x (a loss gradient, a policy-gradient
term) get the same numbers as `x.backward(gx)` from one C call over the solve's own output buffer.

The mathematics is the autograd path's (implicit differentiation of the KKT conditions at the solution, working
rows = equalities and strictly complementary active rows, `gi_qp_vjp`); instances the C adjoint declines (P only
semi-definite, dependent working rows, residual above its test) get the torch adjoint of `solver.py`.  Instances
whose status is not SOLVED get zero gradients, as with autograd.
"""

from __future__ import annotations

import weakref

import numpy as np
import torch
from torch import Tensor

from a3cqp_rl.qp.exceptions import QPGradientError, QPShapeError
from a3cqp_rl.qp.solver import QPSolution, _as_tensor, _backward_torch, _stack_rows, _strides

__all__ = ["qp_vjp", "QPGrad", "GRAD_NAMES", "with_grad", "dual_with_grad"]

GRAD_NAMES = ("P", "q", "A", "b", "G", "h", "lb", "ub")
"""The arguments of `solve_qp` a `QPGrad` has a field for, in order."""
_NDIM = (3, 2, 3, 2, 3, 2, 2, 2)
_F64 = torch.float64


class _GradField:
    """One gradient of a QPGrad, made from its buffer when first read."""

    def __init__(self, k: int) -> None:
        self.k = k
        self.__doc__ = f"Gradient with respect to `{GRAD_NAMES[k]}` (its shape), or None if it was not given or not asked for."

    def __get__(self, g: "QPGrad | None", owner: type | None = None):  # noqa: ANN204
        return self if g is None else g._get(self.k)


class QPGrad:
    """Gradients of Σ gx·x* with respect to the arguments of one `solve_qp` call, each in that argument's shape
    (summed over the batch for an argument shared by it: unbatched, or of batch size 1); float64."""

    __slots__ = ("_out", "_spec", "_cache")

    def __init__(self, out: np.ndarray, spec: list) -> None:
        self._out, self._spec, self._cache = out, spec, [None] * 8

    def _get(self, k: int) -> Tensor | None:
        v = self._cache[k]
        if v is None and self._spec[k] is not None:
            off, count, shape, _ = self._spec[k]
            v = self._cache[k] = torch.from_numpy(self._out[off : off + count].reshape(shape))
        return v

    P, q, A, b, G, h, lb, ub = (_GradField(k) for k in range(8))

    def __repr__(self) -> str:
        return "QPGrad(" + ", ".join(f"{nm}={tuple(self._spec[k][2]) if self._spec[k] else None}"
                                     for k, nm in enumerate(GRAD_NAMES)) + ")"


def qp_vjp(sol: QPSolution, gx: Tensor, wrt: tuple[str, ...] | list[str] | str | None = None) -> QPGrad:
    """Gradients of Σ gx·x* (gx [B, n], the cotangent of `sol.x`) with respect to the QP data of the
    `solve_qp` call that returned `sol`, by implicit differentiation of its KKT conditions (module docstring).

    `sol` must come from the C route without autograd (float64 CPU tensors, no argument requiring grad);
    `wrt` restricts the gradients computed to those arguments (names of `GRAD_NAMES`; default all given).
    Raises QPGradientError when `sol` carries no problem data or that data was changed in place since.
    """
    data = sol._data
    if data is None:
        raise QPGradientError("qp_vjp needs a solution of the C route solved without autograd (float64 CPU "
                              "tensors, no argument requiring grad); for others call x.backward(gx)")
    lib, args, versions = data[:3]
    P, q, A, b, G, h, lb, ub = args
    if (P._version, q._version, -1 if A is None else A._version, -1 if b is None else b._version,
            -1 if G is None else G._version, -1 if h is None else h._version, -1 if lb is None else lb._version,
            -1 if ub is None else ub._version) != versions:
        nm = next(nm for t, v, nm in zip(args, versions, GRAD_NAMES) if t is not None and t._version != v)
        raise QPGradientError(f"{nm} was changed in place after the solve: its gradient would be of other data")
    # Fields read from the solution are views of the buffer read here (made at version 0).
    for f, nm in ((sol._x, "x"), (sol._y, "y"), (sol._z, "z"), (sol._z_lb, "z_lb"), (sol._z_ub, "z_ub")):
        if f is not None and f._version:
            raise QPGradientError(f"the solution's {nm} was changed in place: it is what the gradient is computed from")
    B, n, p, m = sol._dims
    if type(gx) is not Tensor:
        gx = _as_tensor(gx, "gx")
    if gx.dtype is not _F64 or not gx.is_cpu or gx.shape != (B, n) or not gx.is_contiguous():
        if gx.shape not in ((B, n), (n,), (1, n)):
            raise QPShapeError(f"gx must be [{B}, {n}] (the shape of x), got {tuple(gx.shape)}")
        gx = gx.detach().to(device="cpu", dtype=_F64).expand(B, n).contiguous()
    if wrt is not None and type(wrt) is not tuple:
        wrt = (wrt,) if isinstance(wrt, str) else tuple(wrt)
    # The layout of the gradients depends only on the sizes, which arguments were given and their shapes (on the
    # direct path every given argument is [B, ...]), so it is made once per such key.
    ptrs = data[3]
    if len(data) == 4:  # `_fast_c`: every given argument batched and contiguous, read by C where it lies
        strides = (n * n, p * n, m * n, m, n, n)
        key = (B, n, p, m, wrt, A is None, G is None, lb is None, ub is None)
    else:  # other layouts: the addresses and batch strides of the arrays C read (copies kept alive by the solution)
        strides = data[4]
        key = (B, n, p, m, wrt, strides, tuple(None if t is None else tuple(t.shape) for t in args))
    hit = _LAYOUTS.get(key)
    if hit is None:
        if len(_LAYOUTS) > 256:
            _LAYOUTS.clear()
        hit = _LAYOUTS[key] = _layout(args, strides, wrt, B, n, p, m)
    spec, layout, total = hit
    out = np.empty(total + B)
    if lib.vjp(B, n, p, m, *ptrs, sol._buf, gx.data_ptr(), layout, out):  # (arrays go to C as they are)
        _declined(sol, args, gx, out, spec, total)
    return QPGrad(out, spec)


class _SolvedX(torch.autograd.Function):
    """x of a solution of the direct C path, differentiable through `qp_vjp` (the arguments are its inputs)."""

    @staticmethod
    def forward(ctx, sol, inner, *args):  # type: ignore[override]
        ctx.sol, ctx.inner = weakref.ref(sol), inner
        x = torch.from_numpy(inner._np("_x"))
        # saved so that autograd's version check refuses a backward after x was changed in place (x.add_(...)): the
        # adjoint reads x's buffer, and the solution object that would catch it is often gone by then
        ctx.save_for_backward(x)
        return x

    @staticmethod
    def backward(ctx, gx):  # type: ignore[override]
        ctx.saved_tensors  # noqa: B018 (raises if x was changed in place)
        if torch.is_grad_enabled():
            raise QPGradientError("solve_qp's C route gives first derivatives only (its adjoint is not itself "
                                  "differentiable): for create_graph=True or second derivatives solve with "
                                  "backend='torch'")
        need = ctx.needs_input_grad
        wrt = _WRT.get(need)
        if wrt is None:
            wrt = _WRT[need] = tuple(nm for nm, nd in zip(GRAD_NAMES, need[2:]) if nd)
        sol = ctx.sol()  # while the user's solution lives, its fields are checked for in-place changes
        g = qp_vjp(sol if sol is not None else ctx.inner, gx, wrt)
        get = g._get
        return None, None, get(0), get(1), get(2), get(3), get(4), get(5), get(6), get(7)


_WRT: dict[tuple[bool, ...], tuple[str, ...]] = {}
"""needs_input_grad of `_SolvedX` -> the names asked of `qp_vjp` (the same few patterns recur)."""


def with_grad(sol: QPSolution) -> QPSolution:
    """`sol` (of `_fast_c`, arguments requiring grad) with its x an autograd output whose backward is `qp_vjp`."""
    # The node holds a second solution over the same buffer and only a weak reference to `sol`: holding `sol`
    # would make a cycle through its x.
    inner = QPSolution._from_buffer(sol._buf, sol._addr, *sol._dims)
    inner._data = sol._data
    sol._x = _SolvedX.apply(sol, inner, *sol._data[1])
    return sol


def dual_with_grad(sol: QPSolution, name: str) -> Tensor:
    """Field `name` ("_y", "_z", "_z_lb", "_z_ub") of a `with_grad` solution, as an output whose backward refuses: a
    loss through a multiplier must not silently lose that part of its gradient."""
    return _DualOfC.apply(sol, name, *sol._data[1])


class _DualOfC(torch.autograd.Function):
    """A multiplier of a solution of the direct C path: its adjoint covers x only, so a gradient through it raises."""

    @staticmethod
    def forward(ctx, sol, name, *args):  # type: ignore[override]
        return torch.from_numpy(sol._np(name))  # a view of the solver's buffer, as the field would be

    @staticmethod
    def backward(ctx, g):  # type: ignore[override]
        raise QPGradientError("solve_qp's C route differentiates x only: for gradients through the multipliers (y, "
                              "z, z_lb, z_ub) solve with backend='torch'")


_LAYOUTS: dict[tuple, tuple[list, int, int]] = {}
"""Layout key (see `qp_vjp`) -> (per-argument (offset, count, shape, per instance) or None, address of the int64
layout array of gi_qp_vjp, doubles of gradients before the adjoint statuses)."""


def _layout(args: tuple, strides: tuple, wrt: tuple[str, ...] | None, B: int, n: int, p: int, m: int) -> tuple[list, int, int]:
    """Where each gradient goes in the output buffer, and gi_qp_vjp's layout array (module `_LAYOUTS`)."""
    if wrt is not None and any(nm not in GRAD_NAMES for nm in wrt):
        raise QPShapeError(f"wrt names arguments of solve_qp {GRAD_NAMES}, got {tuple(wrt)}")
    sizes = (n * n, n, p * n, p, m * n, m, n, n)
    spec, offs, ostr, total = [], [], [], 0
    for k, t in enumerate(args):
        if t is None or (wrt is not None and GRAD_NAMES[k] not in wrt):
            spec.append(None), offs.append(-1), ostr.append(0)
            continue
        per = B != 1 and t.dim() == _NDIM[k] and t.shape[0] == B  # a gradient per instance, else summed
        count = B * sizes[k] if per else sizes[k]
        spec.append((total, count, tuple(t.shape), per)), offs.append(total), ostr.append(sizes[k] if per else 0)
        total += count
    return spec, _strides((*strides, n, *offs, *ostr, total, 0)), total


def _declined(sol: QPSolution, args: tuple, gx: Tensor, out: np.ndarray, spec: list, total: int) -> None:
    """The torch adjoint for the instances the C adjoint declined, written into (or added to) `out`."""
    B, n, p, m = sol._dims
    left = np.flatnonzero(out[total:].view(np.int64))
    idx = torch.from_numpy(left)
    k = left.size

    def pick(t: Tensor | None, nd: int) -> Tensor | None:
        if t is None:
            return None
        t = t.unsqueeze(0) if t.dim() == nd - 1 else t
        return t.expand(B, *t.shape[1:]).index_select(0, idx)

    P, q, A, b, G, h, lb, ub = (pick(t, nd) for t, nd in zip(args, _NDIM))
    if A is None:
        A, b = gx.new_zeros(k, 0, n), gx.new_zeros(k, 0)
    G_all, h_all = _stack_rows(G, h, lb, ub, k, n, gx)
    has_lb, has_ub = lb is not None, ub is not None
    x = torch.from_numpy(sol._np("_x")[left])
    y = torch.from_numpy(np.ascontiguousarray(sol._np("_y")[left]))
    z = [sol._np("_z")[left]] + ([sol._np("_z_lb")[left]] if has_lb else []) + ([sol._np("_z_ub")[left]] if has_ub else [])
    z_all = torch.from_numpy(np.concatenate(z, 1))
    need = tuple(spec[j] is not None for j in range(4)) + (spec[4] is not None, True)
    gP, gq, gA, gb, gG_all, gh_all = _backward_torch(P, A, G_all, h_all, x, y, z_all, gx.index_select(0, idx), need)
    lb_h = gh_all[:, m : m + n] if has_lb else None
    parts = (gP, gq, gA, gb, gG_all[:, :m] if gG_all is not None else None, gh_all[:, :m],
             None if lb_h is None else -lb_h, gh_all[:, m + n * has_lb :] if has_ub else None)
    for j, g in enumerate(parts):
        if spec[j] is None:
            continue
        off, count, _, per = spec[j]
        g = g.reshape(k, -1).numpy()
        if per:
            out[off : off + count].reshape(B, -1)[left] = g
        else:
            out[off : off + count] += g.sum(0)
