"""`solve_qp`: batched dense QPs, differentiable through the KKT conditions, with a status per instance.

Problem, for each element of a batch [B] with the same sizes::

    minimise ½ xᵀ P x + qᵀ x   subject to   A x = b,   G x ≤ h,   lb ≤ x ≤ ub.

Routes (`backend=`; see `status.py` for which inputs give which status, on every route alike):

- ``"c"``: `native/gi_qp.c`, a dense Goldfarb-Idnani dual active set per instance in one C call for
  the whole batch (input checks, bounds, the active set and its KKT certificate).  It solves every
  strictly convex instance (P ≻ 0) it can certify; the rest (P only semi-definite or indefinite,
  dependent active rows, infeasible or unbounded candidates) goes to the torch route, instance by
  instance.  CPU tensors only.
- ``"torch"``: `batched.py`, the whole batch in batched torch ops on any device: input checks,
  convexity test, a primal-dual active set, then an interior point with infeasibility and
  unboundedness certificates and an exact polish.
- ``"auto"`` (default): ``"c"`` for CPU tensors when the C routine is available, else ``"torch"``.
  The C routine is unavailable without a C compiler or with the environment variable
  A3CQP_NATIVE_QP=0 (a default override for whole programs); an explicit ``backend="c"`` then raises.

Why these two: at the controller's size (n ≈ 13, m ≈ 30) a whole active-set solve is a few µs of
arithmetic, so the C route's cost is its call: at B = 1 this module goes from torch tensors to the C
call and back without intermediate tensors (`_forward_c`), and the returned `QPSolution` turns its
numpy buffers into tensors only when a field is read.  The torch route is what runs on GPUs and
without a compiler.  Measured when a third, numpy copy of the active set was removed (2026-11-24,
1 thread, µs per QP, C / numpy / torch): B = 1 default instances 31 / 65 / 190, heavily constrained
32 / 123 / 857; B = 64 2.0 / 20 / 12 and 5.0 / 57 / 277: where a compiler exists the numpy copy never
ran, and where none exists the controller runs its Python backend anyway.

Every route solves in float64; float32 (or lower) inputs are solved in float64, rounded, and re-checked
against `tol` in the input's precision (TOLERANCE_NOT_MET if the rounded answer misses it).

Backward: implicit differentiation of the KKT system at the solution (as OptNet/qpth), with the
active set read from the duals and slacks (z > h − Gx): the C adjoint (`gi_qp_vjp`) where the C
route solved the batch and P ≻ 0, else the torch adjoint (LU / Schur / augmented Lagrangian, `kkt.py`).
Gradients flow to every tensor argument through x (and, off the direct C path, the multipliers) of SOLVED
instances; nothing is unrolled.  Without
autograd, `vjp.qp_vjp(solution, gx)` gives the same gradients of a C-route solution from one C call.

Code: `kkt.py` (working-set solves, the KKT certificate), `active_set.py`, `interior_point.py`,
`batched.py` (the torch route), `native/` (the C route), this file (arguments, dispatch, autograd).
"""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor

from a3cqp_rl.native_build import address
from a3cqp_rl.qp import native
from a3cqp_rl.qp.batched import solve_torch
from a3cqp_rl.qp.exceptions import QPBackendError, QPGradientError, QPShapeError
from a3cqp_rl.qp.kkt import LU_MAX_BATCH, eq_solve_alm, kkt_certified, kkt_lu, kkt_schur, mv
from a3cqp_rl.qp.status import QPStatus

__all__ = ["QPStatus", "QPSolution", "solve_qp", "BACKENDS", "MAX_STEPS"]

BACKENDS = ("auto", "c", "torch")
"""Values of `solve_qp(backend=...)`."""
MAX_STEPS = 100
"""Active-set steps of the C route (one k × k solve each) before an instance goes to the torch route:
Goldfarb-Idnani is finite (each step adds or drops a row); heavily constrained controller-sized
instances need 10-30, so the budget only stops numerical cycling."""
_F64 = torch.float64


class _Field:
    """A QPSolution field read through `_get` (made from the C route's output buffer when first read)."""

    def __init__(self, doc: str) -> None:
        self.__doc__ = doc

    def __set_name__(self, owner: type, name: str) -> None:
        self.slot = "_" + name

    def __get__(self, sol: "QPSolution | None", owner: type | None = None):  # noqa: ANN204
        return self if sol is None else sol._get(self.slot)


class QPSolution:
    """Solution of a batch of QPs; duals follow L = ½xᵀPx + qᵀx + yᵀ(Ax − b) + zᵀ(Gx − h) + z_lbᵀ(lb − x) + z_ubᵀ(x − ub).

    Fields are tensors in the dtype of `q` (status and iterations int64).  On the C route they are views
    of the solver's output buffer, made when first read (a tensor costs ~1 µs at B = 1).
    """

    __slots__ = ("_x", "_y", "_z", "_z_lb", "_z_ub", "_status", "_iterations", "_dtype", "_buf", "_addr", "_dims", "_data",
                 "__weakref__")

    def __init__(self, x: Tensor, y: Tensor, z: Tensor, z_lb: Tensor, z_ub: Tensor, status: Tensor,
                 iterations: Tensor) -> None:
        self._x, self._y, self._z, self._z_lb, self._z_ub = x, y, z, z_lb, z_ub
        self._status, self._iterations = status, iterations
        self._dtype = x.dtype
        self._buf = self._data = None

    @classmethod
    def _from_buffer(cls, buf: np.ndarray, addr: int, B: int, n: int, p: int, m: int) -> "QPSolution":
        """A solution over gi_qp_solve's output buffer: x [B·n] | duals [B·(p + m + 2n)] | status [B] | solves [B]
        (addr: its data address, or None where it was not taken: the C functions take the array itself)."""
        sol = cls.__new__(cls)
        sol._buf, sol._addr, sol._dims, sol._dtype = buf, addr, (B, n, p, m), _F64
        sol._x = sol._y = sol._z = sol._z_lb = sol._z_ub = sol._status = sol._iterations = sol._data = None
        return sol

    def _np(self, name: str) -> np.ndarray:
        """numpy view of one field of the output buffer."""
        B, n, p, m = self._dims
        buf, nout = self._buf, p + m + 2 * n
        if name == "_x":
            return buf[: B * n].reshape(B, n)
        if name in ("_status", "_iterations"):
            k = B * (n + nout) + (B if name == "_iterations" else 0)
            return buf[k : k + B].view(np.int64)
        lo, hi = {"_y": (0, p), "_z": (p, p + m), "_z_lb": (p + m, p + m + n), "_z_ub": (p + m + n, nout)}[name]
        return self._duals()[:, lo:hi]

    def _get(self, name: str) -> Tensor:
        v = getattr(self, name)
        if v is None:
            if self._x is not None and self._x.requires_grad and name not in ("_status", "_iterations"):
                v = _dual_with_grad(self, name)  # a C solve differentiated: a multiplier that refuses a gradient
            else:
                v = torch.from_numpy(self._np(name))
            setattr(self, name, v)
        return v

    @property
    def x(self) -> Tensor:
        """Primal solution [B, n] (zero where no answer exists: see `status`)."""
        v = self._x
        if v is None:  # the common first read, without `_get`'s lookups (~0.3 µs of a B = 1 solve's ~8)
            B, n = self._dims[:2]
            v = self._x = torch.from_numpy(self._buf[: B * n].reshape(B, n))
        return v

    y = _Field("Multipliers of A x = b [B, p].")
    z = _Field("Multipliers (≥ 0) of G x ≤ h [B, m].")
    z_lb = _Field("Multipliers (≥ 0) of lb ≤ x [B, n] (zero where lb is absent or −inf).")
    z_ub = _Field("Multipliers (≥ 0) of x ≤ ub [B, n] (zero where ub is absent or +inf).")
    status = _Field("QPStatus code per instance [B] (int64).")
    iterations = _Field("KKT factorisations (active-set steps + interior-point iterations) per instance [B] (int64).")

    @property
    def z_shape(self) -> tuple[int, int]:
        """Shape (B, m) of `z` (without making the tensor on the C route)."""
        if self._buf is not None:
            return self._dims[0], self._dims[3]
        return tuple(self._z.shape)

    @property
    def solved(self) -> Tensor:
        """Boolean mask [B] of instances with status SOLVED."""
        return self.status == QPStatus.SOLVED

    def _duals(self) -> np.ndarray:
        """numpy view [B, p + m + 2n] of the output buffer's multipliers (y | z | z_lb | z_ub)."""
        B, n, p, m = self._dims
        return self._buf[B * n : B * (n + p + m + 2 * n)].reshape(B, p + m + 2 * n)

    def forget(self, rows: np.ndarray | list[int]) -> None:
        """Zero the multipliers of the instances `rows` in place, so a warm start from this solution starts them cold."""
        if self._buf is not None:
            self._duals()[rows] = 0.0
            return
        idx = torch.as_tensor(rows, dtype=torch.long)
        with torch.no_grad():
            for t in (self._y, self._z, self._z_lb, self._z_ub):
                t.index_fill_(0, idx, 0.0)

    _FIELDS = ("x", "y", "z", "z_lb", "z_ub", "status", "iterations")

    def _parts(self) -> tuple[np.ndarray, ...]:
        """numpy views [B, ...] of a C solve's output buffer: x, duals (y | z | z_lb | z_ub), status, solves."""
        B = self._dims[0]
        return self._np("_x"), self._duals(), self._buf[-2 * B:-B].reshape(B, 1), self._buf[-B:].reshape(B, 1)

    def take(self, rows: np.ndarray) -> "QPSolution":
        """The solution of the instances `rows` only (copies): a warm start for those QPs alone."""
        if self._buf is not None:  # a buffer in the C layout again, so that the next solve reads it without copies
            B, n, p, m = self._dims
            buf = np.concatenate([a[rows].reshape(-1) for a in self._parts()])
            return QPSolution._from_buffer(buf, None, len(rows), n, p, m)
        return QPSolution(*(getattr(self, f)[torch.as_tensor(rows, dtype=torch.long)] for f in self._FIELDS))

    def put(self, rows: np.ndarray, part: "QPSolution") -> "QPSolution":
        """A copy of this solution with the instances `rows` replaced by `part`'s (in that order); a C solve's buffer
        stays one (the next solve then reads it without copies). Never in place: this solution's fields may be
        tensors a caller holds."""
        if self._buf is not None and part._buf is not None and self._dims[1:] == part._dims[1:]:
            out = QPSolution._from_buffer(self._buf.copy(), None, *self._dims)
            for whole, sub in zip(out._parts(), part._parts()):
                whole[rows] = sub
            return out
        idx = torch.as_tensor(rows, dtype=torch.long)
        fields = []
        for f in self._FIELDS:
            v = getattr(self, f).clone()
            v[idx] = getattr(part, f)
            fields.append(v)
        return QPSolution(*fields)

    @classmethod
    def zeros_like(cls, sol: "QPSolution", batch: int) -> "QPSolution":
        """A solution of `batch` instances shaped as `sol`'s, every field zero (a cold warm start)."""
        if sol._buf is not None:
            _, n, p, m = sol._dims
            return cls._from_buffer(np.zeros(batch * (3 * n + p + m + 2)), None, batch, n, p, m)
        return cls(*(getattr(sol, f).new_zeros((batch, *getattr(sol, f).shape[1:])) for f in cls._FIELDS))

    def __repr__(self) -> str:
        return f"QPSolution(x={self.x!r}, status={self.status!r})"


# ----------------------------------------------------------------------------------------------
# Arguments
# ----------------------------------------------------------------------------------------------


def _as_tensor(t: object, name: str) -> Tensor | None:
    """A QP argument as a tensor: tensors as they are, numpy arrays (and nested lists) converted."""
    if t is None or isinstance(t, Tensor):
        return t
    if isinstance(t, (np.ndarray, list, tuple, float, int, np.floating)):
        a = np.asarray(t)
        if a.dtype.kind not in "fiub":
            raise QPShapeError(f"{name} must hold numbers, got a numpy array of dtype {a.dtype}")
        return torch.from_numpy(np.ascontiguousarray(a, dtype=a.dtype if a.dtype.kind == "f" else np.float64))
    raise QPShapeError(f"{name} must be a torch.Tensor or a numpy array, got {type(t).__name__}")


def _batched(t: Tensor | None, name: str, ndim: int, batch: int, dtype: torch.dtype, device: torch.device) -> Tensor | None:
    """Check dims, dtype and device of a QP argument and expand an unbatched one to the batch size."""
    if t is None:
        return None
    if t.dtype != dtype:
        raise QPShapeError(f"{name} has dtype {t.dtype}, expected {dtype} (the dtype of q)")
    if (t.is_cpu and device.type != "cpu") or (not t.is_cpu and t.device != device):
        raise QPShapeError(f"{name} is on {t.device}, expected {device} (the device of q)")
    if t.dim() == ndim - 1:
        t = t.unsqueeze(0)
    if t.dim() != ndim:
        raise QPShapeError(f"{name} must have {ndim} dims [B, ...] or {ndim - 1} (shared by the batch), got shape {tuple(t.shape)}")
    if t.shape[0] == 1 and batch > 1:
        t = t.expand(batch, *t.shape[1:])
    elif t.shape[0] != batch:
        raise QPShapeError(f"{name} has batch size {t.shape[0]}, expected {batch}")
    return t


def _resolve_backend(backend: str, q: Tensor) -> native.NativeQP | None:
    """The C routine to use, or None for the torch route; unknown or impossible backends raise."""
    if backend == "torch":
        return None
    if backend not in BACKENDS:
        if backend == "numpy":
            raise QPBackendError("backend 'numpy' no longer exists: use 'c' (compiled) or 'torch' (any device)")
        raise QPBackendError(f"backend must be one of {BACKENDS}, got {backend!r}")
    if not q.is_cpu:
        if backend == "c":
            raise QPBackendError(f"backend='c' solves CPU tensors, got tensors on {q.device}; use 'torch' or 'auto'")
        return None
    lib = native.load()
    if lib is None and backend == "c":
        raise QPBackendError("backend='c' is unavailable: the C routine did not build (no C compiler, or "
                             "A3CQP_NATIVE_QP=0); use 'torch' or 'auto'")
    return lib


_EMPTY_EQ: dict[tuple, tuple[Tensor, Tensor]] = {}


def _no_equalities(B: int, n: int, like: Tensor) -> tuple[Tensor, Tensor]:
    """Empty A [B, 0, n] and b [B, 0], cached per shape/dtype/device (a tensor without elements cannot change)."""
    key = (B, n, like.dtype, like.device)
    eq = _EMPTY_EQ.get(key)
    if eq is None:
        if len(_EMPTY_EQ) > 64:
            _EMPTY_EQ.clear()
        eq = _EMPTY_EQ[key] = (like.new_zeros(B, 0, n), like.new_zeros(B, 0))
    return eq


def _stack_rows(G: Tensor | None, h: Tensor | None, lb: Tensor | None, ub: Tensor | None, B: int, n: int,
                like: Tensor) -> tuple[Tensor, Tensor]:
    """G x ≤ h, −x ≤ −lb, x ≤ ub as one (G_all [B, m + ·, n], h_all); infinite entries are handled downstream."""
    rows_G, rows_h = [], []
    if G is not None:
        rows_G.append(G)
        rows_h.append(h)
    if lb is not None or ub is not None:
        eye = torch.eye(n, dtype=like.dtype, device=like.device).expand(B, n, n)
        if lb is not None:
            rows_G.append(-eye)
            rows_h.append(-lb)
        if ub is not None:
            rows_G.append(eye)
            rows_h.append(ub)
    if not rows_G:
        return like.new_zeros(B, 0, n), like.new_zeros(B, 0)
    if len(rows_G) == 1:
        return rows_G[0], rows_h[0]
    return torch.cat(rows_G, 1), torch.cat(rows_h, 1)


# ----------------------------------------------------------------------------------------------
# The C route
# ----------------------------------------------------------------------------------------------

_STRIDES: dict[tuple[int, ...], tuple[np.ndarray, int]] = {}
_RETIRED: list[dict] = []


def _strides(key: tuple[int, ...]) -> int:
    """Address of the int64 stride array of a call (cached, arrays kept alive: the same few layouts recur
    every control step)."""
    hit = _STRIDES.get(key)
    if hit is None:
        if len(_STRIDES) > 256:  # addresses handed out stay valid: old arrays are kept, only not found again
            _RETIRED.append(_STRIDES.copy())
            _STRIDES.clear()
            _FAST_STRIDES.clear()
        arr = np.array(key, dtype=np.int64)
        hit = _STRIDES[key] = (arr, address(arr))
    return hit[1]


def _c_arg(t: Tensor | None, ndim: int, B: int) -> tuple[Tensor | None, int, int]:
    """(tensor kept alive, data address, batch stride in doubles) of a float64 CPU argument for gi_qp_solve."""
    if t is None:
        return None, 0, 0
    if t.dim() == ndim:  # batched
        if t.shape[0] != B and t.shape[0] != 1:
            raise QPShapeError(f"an argument has batch size {t.shape[0]}, expected {B}")
        if t.is_contiguous():
            return t, t.data_ptr(), (t.numel() // t.shape[0] if t.shape[0] == B and B > 1 else 0)
        if t.stride(0) == 0 and t[0].is_contiguous():  # expanded: one array for the whole batch
            return t, t.data_ptr(), 0
        t = t.contiguous()
        return t, t.data_ptr(), t.numel() // B
    t = t.contiguous()  # unbatched: shared
    return t, t.data_ptr(), 0


def _forward_c(
    lib: native.NativeQP, P: Tensor, q: Tensor, A: Tensor | None, b: Tensor | None, G: Tensor | None,
    h: Tensor | None, lb: Tensor | None, ub: Tensor | None, B: int, n: int, p: int, m: int,
    warm: tuple[np.ndarray, int, int] | None, tol: float,
) -> tuple[np.ndarray, int, int, list]:
    """One gi_qp_solve call on float64 CPU tensors (any batch layout); returns (output buffer, its address, worst
    status, the arguments as passed to C: (tensor kept alive, address, batch stride) each)."""
    keep = [_c_arg(P, 3, B), _c_arg(q, 2, B), _c_arg(A, 3, B), _c_arg(b, 2, B), _c_arg(G, 3, B), _c_arg(h, 2, B),
            _c_arg(lb, 2, B), _c_arg(ub, 2, B)]
    nout = p + m + 2 * n
    out = np.empty(B * (n + nout + 2))
    o = address(out)
    z0, z0_stride = (warm[1], warm[2]) if warm is not None else (0, 0)
    worst = lib.solve(B, n, p, m, *(k[1] for k in keep), z0, _strides((*(k[2] for k in keep), z0_stride)), tol,
                      MAX_STEPS, o)
    if worst < 0:
        raise MemoryError("a3cqp_rl.qp: the C route could not allocate its workspace")
    return out, o, worst, keep


def _warm_duals(warm_start: "QPSolution", B: int, n: int, p: int, m: int) -> tuple[np.ndarray, int, int]:
    """Warm-start multipliers for the C route as (array kept alive, address of z | z_lb | z_ub, stride)."""
    if warm_start._buf is not None and warm_start._dims == (B, n, p, m):  # a C solve's own buffer: no copies
        base = warm_start._addr if warm_start._addr is not None else address(warm_start._buf)
        return warm_start._buf, base + 8 * (B * n + p), p + m + 2 * n
    parts = [warm_start.z, warm_start.z_lb, warm_start.z_ub]
    want = ((B, m), (B, n), (B, n))
    for t, w, nm in zip(parts, want, ("z", "z_lb", "z_ub")):
        if tuple(t.shape) != w:
            raise QPShapeError(f"warm_start.{nm} has shape {tuple(t.shape)}, expected {w}")
    z0 = np.ascontiguousarray(torch.cat([t.detach().to(_F64).cpu() for t in parts], 1).numpy())
    return z0, address(z0), m + 2 * n


_FAST_STRIDES: dict[tuple[int, ...], int] = {}
"""(n, p, m, warm stride) -> address of the stride array of `_fast_c`'s layout (batched contiguous arguments)."""


def _fast_c(lib: native.NativeQP, P: Tensor, q: Tensor, A: Tensor | None, b: Tensor | None, G: Tensor | None,
            h: Tensor | None, lb: Tensor | None, ub: Tensor | None, warm_start: QPSolution | None, tol: float,
            max_iter: int, active_set_iter: int | None, hand_on: bool = True) -> QPSolution | None:
    """The C route for the common call (every argument a batched, contiguous float64 CPU tensor of one batch
    size), straight from the tensors' data to gi_qp_solve and back; None when the call does not fit (the general
    path then checks, explains and converts).  q is a float64 CPU tensor (checked by the caller)."""
    # At B = 1 each check is ~50 ns and the whole Python side of a solve ~3 µs: the checks are written out
    # (no nested function calls) and the output buffer goes to C as the array itself (no address taken here).
    if type(P) is not Tensor or P.dtype is not _F64 or q.dim() != 2 or not (P.is_cpu and P.is_contiguous() and q.is_contiguous()):
        return None
    B, n = q.shape
    if P.shape != (B, n, n):
        return None
    p = m = 0
    pA = pb = pG = ph = pl = pu = 0
    if G is not None:
        if (type(G) is not Tensor or type(h) is not Tensor or G.dtype is not _F64 or h.dtype is not _F64
                or not (G.is_cpu and h.is_cpu and G.is_contiguous() and h.is_contiguous())):
            return None
        m = G.shape[1] if G.dim() == 3 else -1
        if G.shape != (B, m, n) or h.shape != (B, m):
            return None
        pG, ph = G.data_ptr(), h.data_ptr()
    if A is not None:
        if (type(A) is not Tensor or type(b) is not Tensor or A.dtype is not _F64 or b.dtype is not _F64
                or not (A.is_cpu and b.is_cpu and A.is_contiguous() and b.is_contiguous())):
            return None
        p = A.shape[1] if A.dim() == 3 else -1
        if A.shape != (B, p, n) or b.shape != (B, p):
            return None
        pA, pb = A.data_ptr(), b.data_ptr()
    if lb is not None:
        if type(lb) is not Tensor or lb.dtype is not _F64 or lb.shape != (B, n) or not (lb.is_cpu and lb.is_contiguous()):
            return None
        pl = lb.data_ptr()
    if ub is not None:
        if type(ub) is not Tensor or ub.dtype is not _F64 or ub.shape != (B, n) or not (ub.is_cpu and ub.is_contiguous()):
            return None
        pu = ub.data_ptr()
    z0 = zs = 0
    keep = None
    if warm_start is not None:
        keep, z0, zs = _warm_duals(warm_start, B, n, p, m)
    buf = np.empty(B * (3 * n + p + m + 2))
    key = (n, p, m, zs)
    sa = _FAST_STRIDES.get(key)
    if sa is None:
        sa = _FAST_STRIDES[key] = _strides((n * n, n, p * n, p, m * n, m, n, n, zs))
    pP = P.data_ptr()
    worst = lib.solve(B, n, p, m, pP, q.data_ptr(), pA, pb, pG, ph, pl, pu, z0, sa, tol, MAX_STEPS, buf)
    del keep
    sol = QPSolution._from_buffer(buf, None, B, n, p, m)
    # What `qp_vjp` needs: the arguments (batched, contiguous), versions to notice in-place changes, what C read.
    sol._data = (lib, (P, q, A, b, G, h, lb, ub),
                 (P._version, q._version, -1 if A is None else A._version, -1 if b is None else b._version,
                  -1 if G is None else G._version, -1 if h is None else h._version,
                  -1 if lb is None else lb._version, -1 if ub is None else ub._version), (pP, pA, pG, ph, pl, pu))
    if worst:
        if worst >= native.HANDED_ON:  # some instances need the torch route (no graph: x's node is `qp_vjp`)
            _settle_handed_on(sol, hand_on, P, q, A, b, G, h, lb, ub, warm_start, tol, max_iter, active_set_iter)
        elif worst < 0:
            raise MemoryError("a3cqp_rl.qp: the C route could not allocate its workspace")
    return sol


# ----------------------------------------------------------------------------------------------
# Canonical forward (autograd path and leftovers of the C route)
# ----------------------------------------------------------------------------------------------


def _solve_canonical(
    lib: native.NativeQP | None, P: Tensor, q: Tensor, A: Tensor, b: Tensor, G: Tensor, h: Tensor,
    z_warm: Tensor | None, tol: float, max_iter: int, active_set_iter: int | None, hand_on: bool = True,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor, tuple | None]:
    """Solve a canonical float64 batch (bounds stacked into G, h); returns x, y, z, status, iterations and
    the C route's output buffer and arguments when it certified every instance (its adjoint then applies), else None."""
    if lib is None:
        return (*solve_torch(P, q, A, b, G, h, z_warm, tol, max_iter, active_set_iter), None)
    B, n = q.shape
    p, m = A.shape[1], G.shape[1]
    warm = None
    if z_warm is not None:
        z0 = np.ascontiguousarray(torch.cat([z_warm.detach(), z_warm.new_zeros(B, 2 * n)], 1).numpy())
        warm = (z0, address(z0), m + 2 * n)
    buf, addr, _, keep = _forward_c(lib, P, q, A, b, G, h, None, None, B, n, p, m, warm, tol)
    c = QPSolution._from_buffer(buf, addr, B, n, p, m)
    st = c._np("_status")
    x, y, z, status, iters = c.x, c.y, c.z, c.status, c.iterations
    if st[st.argmax()] < native.HANDED_ON:
        return x, y, z, status, iters, None if st.any() else (buf, addr, keep)
    if not hand_on:
        _keep_c_verdict(c)
        return x, y, z, status, iters, None
    left = np.flatnonzero(st >= native.HANDED_ON)
    idx = torch.from_numpy(left)
    sub = [t.index_select(0, idx) for t in (P, q, A, b, G, h)]
    zw = z_warm.index_select(0, idx) if z_warm is not None else None
    xs, ys, zs, ss, its = solve_torch(*sub, zw, tol, max_iter, active_set_iter)
    x[idx], y[idx], z[idx], status[idx], iters[idx] = xs, ys, zs, ss, its + iters[idx]
    return x, y, z, status, iters, None


def _backward_torch(P: Tensor, A: Tensor, G: Tensor, h: Tensor, x: Tensor, y: Tensor, z: Tensor, gx: Tensor,
                    need: tuple[bool, ...], gy: Tensor | None = None, gz: Tensor | None = None
                    ) -> tuple[Tensor | None, ...]:
    """Gradients (P, q, A, b, G, h) of Σ gx·x + gy·y + gz·z by the batched torch adjoint (gy, gz: None = 0)."""
    p = A.shape[1]
    Ps = 0.5 * (P + P.mT)
    slack = (h - mv(G, x)).clamp_min(0.0)
    active = z > slack  # strictly complementary part of the active set
    C = torch.cat([A, G], 1) if p else G
    mask = torch.cat([torch.ones_like(y, dtype=torch.bool), active], 1) if p else active
    # Adjoint: [[P, C_Wᵀ], [C_W, 0]] [wx; wν] = [gx; gν_W], i.e. min ½wᵀPw − gxᵀw s.t. C_W w = gν_W; the
    # multipliers of inactive rows stay 0 under a small change, so their gν does not enter.
    zr = torch.zeros_like(C[..., 0])
    gnu = zr
    if gy is not None or gz is not None:
        gnu = torch.cat([zr[:, :p] if gy is None else gy, zr[:, p:] if gz is None else gz], 1)
    g_max = max((float(g.detach().abs().amax()) for g in (gx, gnu) if g.numel()), default=0.0)
    tol_w = 1e-12 * (1.0 + g_max)
    wx = wnu = res = None
    if gx.shape[0] <= LU_MAX_BATCH:
        wx, wnu, res = kkt_lu(Ps, -gx, C, gnu, mask)
    else:
        L, info = torch.linalg.cholesky_ex(Ps)
        if bool((info == 0).all()):
            x_u = torch.cholesky_solve(gx.unsqueeze(-1), L).squeeze(-1)
            wx, wnu, res = kkt_schur(L, x_u, Ps, -gx, C, gnu, mask)
    nu_max = wnu.abs().amax(-1) if wnu is not None and wnu.shape[-1] else 0.0
    if res is None or not bool((res <= tol_w * (1.0 + nu_max)).all()):
        # Singular KKT (dependent active rows, P singular on their null space): the augmented
        # Lagrangian is exact in the limit and stays well posed.
        wx, wnu, _, _ = eq_solve_alm(Ps, -gx, C, gnu, mask, zr, torch.zeros_like(x), 0.1 * tol_w)
    wy, wz = wnu[:, :p], wnu[:, p:]
    nu = torch.cat([y, z * active], 1) if p else z * active
    # Sums of two outer products as one bmm with inner dimension 2: a single pass over the
    # [B, r, n] output instead of four.
    u = torch.stack([wx, x], -2)  # (B, 2, n)
    gP = (torch.stack([x, wx], -1) @ u).mul_(-0.5) if need[0] else None  # −½(x wxᵀ + wx xᵀ)
    gA = gG = None
    if need[2] or need[4]:
        gC = (torch.stack([nu, wnu], -1) @ u).neg_()  # −(ν wxᵀ + wν xᵀ), (B, r, n)
        gA, gG = gC[:, :p], gC[:, p:]
    return gP, -wx, gA, wy, gG, wz


def _backward_c(lib: native.NativeQP, c_run: tuple, B: int, n: int, p: int, m: int, gx: Tensor,
                need: tuple[bool, ...]) -> tuple[Tensor | None, ...] | None:
    """Gradients (P, q, A, b, G, h) of Σ gx·x on canonical rows by `gi_qp_vjp` from the C route's own output
    buffer, per instance; None if the C adjoint declined an instance (the torch adjoint then runs)."""
    buf, addr, keep = c_run
    gx = gx.detach().to(_F64).contiguous()
    sizes = (n * n, n, p * n, p, m * n, m)
    offs, total = [], 0
    for k, size in enumerate(sizes):
        offs.append(total if need[k] else -1)
        total += B * size if need[k] else 0
    out = np.empty(total + B)
    layout = _strides((*(keep[k][2] for k in (0, 2, 4, 5)), 0, 0, n, *offs, -1, -1, *sizes, 1, 1, total, 0))
    if lib.vjp(B, n, p, m, keep[0][1], keep[2][1], keep[4][1], keep[5][1], 0, 0, addr, gx.data_ptr(), layout, address(out)):
        return None
    t = torch.from_numpy(out)
    shapes = ((B, n, n), (B, n), (B, p, n), (B, p), (B, m, n), (B, m))
    return tuple(t[offs[k] : offs[k] + B * sizes[k]].view(shapes[k]) if need[k] else None for k in range(6))


class _QPFunction(torch.autograd.Function):
    """x*(P, q, A, b, G, h) with a backward by implicit differentiation of the KKT conditions."""

    @staticmethod
    def forward(ctx, lib, P, q, A, b, G, h, z_warm, tol, max_iter, active_set_iter, hand_on):  # type: ignore[override]
        # Outputs nothing depends on get None instead of zeros (most callers differentiate x only).
        ctx.set_materialize_grads(False)
        x, y, z, status, iters, c_run = _solve_canonical(lib, P, q, A, b, G, h, z_warm, tol, max_iter, active_set_iter,
                                                         hand_on)
        ctx.lib, ctx.c_run = (lib, c_run) if c_run is not None else (None, None)
        ctx.save_for_backward(P, A, G, h, x, y, z, status)
        # The duals are differentiable too: the torch adjoint's gradients of A and G contain them, so second
        # derivatives need their dependence on the data.
        ctx.mark_non_differentiable(status, iters)
        return x, y, z, status, iters

    @staticmethod
    def backward(ctx, gx, gy, gz, _gs, _gi):  # type: ignore[override]
        P, A, G, h, x, y, z, status = ctx.saved_tensors
        if gx is None:
            gx = torch.zeros_like(x)
        need = ctx.needs_input_grad[1:7]
        # Gradients only flow through the solution of solved instances.
        grads = None
        # the C route certified every instance: its range-space adjoint of x alone (not differentiable itself:
        # with create_graph, or gradients of the duals, the torch adjoint below, whose operations autograd records)
        if ctx.lib is not None and not torch.is_grad_enabled() and gy is None and gz is None:
            grads = _backward_c(ctx.lib, ctx.c_run, x.shape[0], x.shape[1], A.shape[1], G.shape[1], gx, need)
        if grads is None:
            ok = status == QPStatus.SOLVED
            if not bool(ok.all()):
                zero = torch.zeros((), dtype=gx.dtype)
                gx, gy, gz = (g if g is None else torch.where(ok.unsqueeze(-1), g, zero) for g in (gx, gy, gz))
            grads = _backward_torch(P, A, G, h, x, y, z, gx, need, gy, gz)
        return (None, *grads, None, None, None, None, None)


# ----------------------------------------------------------------------------------------------
# solve_qp
# ----------------------------------------------------------------------------------------------


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
    backend: str = "auto",
    hand_on: bool = True,
) -> QPSolution:
    """Solve a batch of QPs min ½xᵀPx + qᵀx s.t. Ax = b, Gx ≤ h, lb ≤ x ≤ ub (differentiable).

    Args:
        P: Hessian [B, n, n] (symmetrised internally), positive semi-definite (else NON_CONVEX).
        q: linear cost [B, n]; its dtype and device are the result's.
        A, b: equality rows [B, p, n] and right-hand side [B, p] (both or neither).
        G, h: inequality rows [B, m, n] and right-hand side [B, m]; h_i ≥ 1e20 or +inf means no row.
        lb, ub: bounds on x [B, n]; entries ≤ −1e20 / ≥ 1e20 (or ∓inf) mean no bound.
        warm_start: a previous QPSolution of same-sized problems; its multipliers seed the active set.
        tol: relative tolerance of every KKT residual, row by row (see `status.py`); default 1e-9 for
            float64 input, 1e-5 for lower precision (solved in float64, checked after rounding).
        max_iter: interior-point iteration budget (torch route: instances the active set leaves).
        active_set_iter: primal-dual active-set iterations of the torch route before its interior
            point (default 15 for B ≤ 32, 10 above).
        backend: "auto", "c" or "torch" (module docstring); unknown or impossible ones raise
            QPBackendError.
        hand_on: the C route hands the instances it cannot decide (degenerate ones, and infeasible ones whose
            Farkas vector it cannot check) on to the torch route, which solves them or certifies that no answer
            exists (~20 ms an instance); False returns them as MAX_ITER instead, for a caller that treats every
            failure alike and cannot wait.

    Any argument may be given unbatched (without the leading B) to share it across the batch, and as a
    numpy array (converted; its dtype must match the others').  Gradients flow to every tensor argument
    through x (implicit differentiation of the KKT system), and through the multipliers except on the direct C
    path, where a gradient through them raises QPGradientError (docs/qp.md).  Returns a `QPSolution` whose `status`
    says per instance whether x is an answer (never raises on a bad instance; see `status.py`).
    """
    _check_settings(tol, max_iter, active_set_iter)
    if torch._C._are_functorch_transforms_active():  # their wrapped tensors have no storage for the C solver to read
        raise QPGradientError("solve_qp does not run under torch.func transforms (vmap, grad, jacrev, ...): it is "
                              "batched already (pass the batch as the leading dimension) and differentiable by "
                              "backward() or torch.autograd.functional.jacobian")
    max_iter = int(max_iter)
    if type(q) is not Tensor:
        q = _as_tensor(q, "q")
    if q.dtype is _F64 and backend == "auto" and q.is_cpu:
        # The control loop's call (float64 CPU tensors): straight to the C routine when every argument is batched and
        # contiguous (`_fast_c`); everything below checks and explains, and is ~1 µs slower at B = 1.
        lib = native.load()
        if lib is not None and (A is None) == (b is None) and (G is None) == (h is None):
            sol = _fast_c(lib, P, q, A, b, G, h, lb, ub, warm_start, 1e-9 if tol is None else float(tol), max_iter,
                          active_set_iter, hand_on)
            if sol is not None:
                if torch.is_grad_enabled() and _needs_grad(P, q, A, b, G, h, lb, ub):
                    return _with_grad(sol)  # x differentiable by `qp_vjp`: one autograd node
                return sol
    qd = q.dim()
    if qd not in (1, 2):
        raise QPShapeError(f"q must be [B, n] or [n], got shape {tuple(q.shape)}")
    dtype = q.dtype
    if not dtype.is_floating_point:
        raise QPShapeError(f"q must be a floating tensor, got {dtype}")
    if (A is None) != (b is None) or (G is None) != (h is None):
        raise QPShapeError("A and b (and G and h) must be given together")
    lib = _resolve_backend(backend, q) if backend != "torch" else None
    tol = float(tol) if tol is not None else (1e-9 if dtype is _F64 else 1e-5)
    grad = torch.is_grad_enabled() and _needs_grad(P, q, A, b, G, h, lb, ub)
    if lib is not None and dtype == _F64:
        # The control loop's call (batched contiguous float64 tensors): straight to the C routine.
        if not grad:
            sol = _fast_c(lib, P, q, A, b, G, h, lb, ub, warm_start, tol, max_iter, active_set_iter, hand_on)
            if sol is not None:
                return sol
        else:  # the same, with x differentiable by `qp_vjp` (one autograd node, none of the general path's work)
            sol = _fast_c(lib, P, q, A, b, G, h, lb, ub, warm_start, tol, max_iter, active_set_iter, hand_on)
            if sol is not None:
                return _with_grad(sol)
    P, A, b, G, h, lb, ub = (t if t is None or isinstance(t, Tensor) else _as_tensor(t, nm)
                             for t, nm in zip((P, A, b, G, h, lb, ub), ("P", "A", "b", "G", "h", "lb", "ub")))
    if lib is not None and not grad and dtype == _F64:
        # Other float64 CPU layouts (unbatched or expanded arguments): the same C call with strides.
        n = q.shape[-1]
        B = q.shape[0] if qd == 2 else 1
        if B == 1:  # q shared or of batch 1: P or G may carry the batch (any other layout: the general path)
            if P.dim() == 3 and P.shape[0] > 1:
                B = P.shape[0]
            elif G is not None and G.dim() == 3 and G.shape[0] > 1:
                B = G.shape[0]
        p = A.shape[-2] if A is not None else 0
        m = G.shape[-2] if G is not None else 0
        if _fast_shapes_ok(P, q, A, b, G, h, lb, ub, B, n, p, m):
            warm = _warm_duals(warm_start, B, n, p, m) if warm_start is not None else None
            buf, addr, worst, keep = _forward_c(lib, P, q, A, b, G, h, lb, ub, B, n, p, m, warm, tol)
            sol = QPSolution._from_buffer(buf, addr, B, n, p, m)
            args = (P, q, A, b, G, h, lb, ub)
            sol._data = (lib, args, tuple(-1 if t is None else t._version for t in args),
                         tuple(keep[k][1] for k in (0, 2, 4, 5, 6, 7)), tuple(keep[k][2] for k in (0, 2, 4, 5, 6, 7)),
                         keep)
            if worst >= native.HANDED_ON:
                _settle_handed_on(sol, hand_on, P, q, A, b, G, h, lb, ub, warm_start, tol, max_iter, active_set_iter)
            return sol
    return _solve_general(lib, P, q, A, b, G, h, lb, ub, warm_start, tol, max_iter, active_set_iter, dtype, grad,
                          hand_on)


def _dual_with_grad(sol: QPSolution, name: str) -> Tensor:
    """`vjp.dual_with_grad` (bound here on first use, as `_with_grad`)."""
    global _dual_with_grad
    from a3cqp_rl.qp.vjp import dual_with_grad

    _dual_with_grad = dual_with_grad
    return dual_with_grad(sol, name)


def _with_grad(sol: QPSolution) -> QPSolution:
    """`vjp.with_grad` (vjp imports this module; bound here on first use)."""
    global _with_grad
    from a3cqp_rl.qp.vjp import with_grad

    _with_grad = with_grad
    return with_grad(sol)


def _needs_grad(P, q, A, b, G, h, lb, ub) -> bool:  # noqa: ANN001
    """Whether any argument requires a gradient."""
    return bool(q.requires_grad or getattr(P, "requires_grad", False)
                or (G is not None and getattr(G, "requires_grad", False)) or (h is not None and getattr(h, "requires_grad", False))
                or (A is not None and (getattr(A, "requires_grad", False) or getattr(b, "requires_grad", False)))
                or (lb is not None and getattr(lb, "requires_grad", False))
                or (ub is not None and getattr(ub, "requires_grad", False)))


def _fast_shapes_ok(P, q, A, b, G, h, lb, ub, B: int, n: int, p: int, m: int) -> bool:  # noqa: ANN001
    """Whether every argument is a float64 CPU tensor of a consistent shape (else the general path checks and explains)."""
    for t, full in ((P, (B, n, n)), (q, (B, n)), (A, (B, p, n)), (b, (B, p)), (G, (B, m, n)), (h, (B, m)), (lb, (B, n)),
                    (ub, (B, n))):
        if t is None:
            continue
        if t.dtype != _F64 or not t.is_cpu:
            return False
        s = t.shape
        if len(s) == len(full):
            if s[1:] != full[1:] or (s[0] != B and s[0] != 1):
                return False
        elif s != full[1:]:
            return False
    return True


def _warm_rows(warm_start: QPSolution | None, has_G: bool, has_lb: bool, has_ub: bool, h_all: Tensor) -> Tensor | None:
    """Warm-start multipliers of the stacked rows (G, then lb, then ub) as one float64 tensor, or None."""
    if warm_start is None or not h_all.shape[1]:
        return None
    parts = ([warm_start.z] if has_G else []) + ([warm_start.z_lb] if has_lb else []) + ([warm_start.z_ub] if has_ub else [])
    return torch.cat([t.detach().to(device=h_all.device, dtype=_F64) for t in parts], 1)


def _finish_on_torch(sol: QPSolution, P, q, A, b, G, h, lb, ub, B: int, n: int, p: int, m: int,  # noqa: ANN001
                     warm_start: QPSolution | None, tol: float, max_iter: int, active_set_iter: int | None) -> None:
    """Solve the instances the C route handed on with the torch route, writing into sol's buffer."""
    st = sol._np("_status")
    left = np.flatnonzero(st >= native.HANDED_ON)
    idx = torch.from_numpy(left)

    def pick(t: Tensor | None, nd: int) -> Tensor | None:
        if t is None:
            return None
        t = t.unsqueeze(0) if t.dim() == nd - 1 else t
        return t.expand(B, *t.shape[1:]).index_select(0, idx)

    Ps, qs, As, bs, Gs, hs, lbs, ubs = (pick(t, nd) for t, nd in ((P, 3), (q, 2), (A, 3), (b, 2), (G, 3), (h, 2), (lb, 2), (ub, 2)))
    k = left.size
    if As is None:
        As, bs = qs.new_zeros(k, 0, n), qs.new_zeros(k, 0)
    G_all, h_all = _stack_rows(Gs, hs, lbs, ubs, k, n, qs)
    zw = _warm_rows(warm_start, Gs is not None, lbs is not None, ubs is not None, h_all)
    zw = zw.index_select(0, idx) if zw is not None else None
    xs, ys, zs, ss, its = solve_torch(Ps, qs, As, bs, G_all, h_all, zw, tol, max_iter, active_set_iter)
    xn = sol._np("_x")
    dn = sol._duals()
    xn[left] = xs.numpy()
    dn[left, :p] = ys.numpy()
    zsn = zs.numpy()
    dn[left, p : p + m] = zsn[:, :m]
    off = m
    dn[left, p + m : p + m + n] = 0.0
    dn[left, p + m + n :] = 0.0
    if lbs is not None:
        dn[left, p + m : p + m + n] = zsn[:, off : off + n]
        off += n
    if ubs is not None:
        dn[left, p + m + n :] = zsn[:, off : off + n]
    st[left] = ss.numpy()
    sol._np("_iterations")[left] += its.numpy()


def _settle_handed_on(sol: QPSolution, hand_on: bool, P, q, A, b, G, h, lb, ub,  # noqa: ANN001
                      warm_start: QPSolution | None, tol: float, max_iter: int, active_set_iter: int | None) -> None:
    """The instances a C-route solution left: solved on the torch route (`hand_on`), else MAX_ITER."""
    if not hand_on:
        _keep_c_verdict(sol)
        return
    B, n, p, m = sol._dims
    with torch.no_grad():
        _finish_on_torch(sol, P, q, A, b, G, h, lb, ub, B, n, p, m, warm_start, tol, max_iter, active_set_iter)


def _keep_c_verdict(sol: QPSolution) -> None:
    """`hand_on=False`: the instances the C route left undecided get MAX_ITER in sol's buffer (x and the multipliers
    0) instead of a torch-route solve."""
    st = sol._np("_status")
    left = st >= native.HANDED_ON
    sol._np("_x")[left] = 0.0
    sol.forget(np.flatnonzero(left))
    st[left] = int(QPStatus.MAX_ITER)


def _check_settings(tol: float | None, max_iter: int, active_set_iter: int | None) -> None:
    """QPShapeError for a `tol` outside (0, 1) (NaN too), a `max_iter` that is not an integer ≥ 1, or a negative
    `active_set_iter`."""
    def integer(v) -> bool:  # noqa: ANN001
        return isinstance(v, (int, np.integer)) and not isinstance(v, bool)

    if tol is not None and not (isinstance(tol, (float, int, np.floating, np.integer)) and 0 < float(tol) < 1):
        raise QPShapeError(f"tol must be a number in (0, 1) (or None: the dtype's default), got {tol!r}")
    if not (integer(max_iter) and max_iter >= 1):
        raise QPShapeError(f"max_iter must be an integer >= 1, got {max_iter!r}")
    if active_set_iter is not None and not (integer(active_set_iter) and active_set_iter >= 0):
        raise QPShapeError(f"active_set_iter must be an integer >= 0 (or None: the default), got {active_set_iter!r}")


def _solve_general(lib: native.NativeQP | None, P, q, A, b, G, h, lb, ub, warm_start: QPSolution | None,  # noqa: ANN001
                   tol: float, max_iter: int, active_set_iter: int | None, dtype: torch.dtype, grad: bool,
                   hand_on: bool = True) -> QPSolution:
    """Every other call: shape checks with messages, float64 working precision, autograd, the torch route."""
    device = q.device
    lead = [(t.shape[0], nm) for t, k, nm in ((P, 3, "P"), (q, 2, "q"), (A, 3, "A"), (b, 2, "b"), (G, 3, "G"),
                                               (h, 2, "h"), (lb, 2, "lb"), (ub, 2, "ub"))
            if t is not None and t.dim() == k]
    sizes = sorted({size for size, _ in lead if size != 1})
    if len(sizes) > 1:
        said = "; ".join(f"{', '.join(nm for size, nm in lead if size == k)}: {k}" for k in sizes)
        raise QPShapeError(f"the arguments' batch sizes differ ({said}); each is [B, ...] with one B, or shared "
                           "(unbatched or of batch 1)")
    B = max(size for size, _ in lead) if lead else 1
    P = _batched(P, "P", 3, B, dtype, device)
    q = _batched(q, "q", 2, B, dtype, device)
    n = q.shape[1]
    if P.shape[1:] != (n, n):
        raise QPShapeError(f"P must be [B, {n}, {n}], got {tuple(P.shape)}")
    A, b, G, h, lb, ub = (_batched(t, nm, nd, B, dtype, device) for t, nm, nd in
                          ((A, "A", 3), (b, "b", 2), (G, "G", 3), (h, "h", 2), (lb, "lb", 2), (ub, "ub", 2)))
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
    low = dtype != _F64
    user_tol = tol
    if low:  # solved in float64, a margin below the tolerance the rounded answer must meet
        tol = tol * 1e-3
        P, q, A, b, G, h, lb, ub = (None if t is None else t.to(_F64) for t in (P, q, A, b, G, h, lb, ub))
        P = _lift_rounded_psd(P, dtype)
    m = G.shape[1] if G is not None else 0
    if A is None:
        A, b = _no_equalities(B, n, q)
    G_all, h_all = _stack_rows(G, h, lb, ub, B, n, q)
    z_warm = _warm_rows(warm_start, G is not None, lb is not None, ub is not None, h_all)
    if z_warm is not None and z_warm.shape != h_all.shape:
        raise QPShapeError(f"warm_start duals have shape {tuple(z_warm.shape)}, expected {tuple(h_all.shape)}")
    args = (z_warm, tol, int(max_iter), None if active_set_iter is None else int(active_set_iter), hand_on)
    if grad:
        x, y, z_all, status, iters = _QPFunction.apply(lib, P, q, A, b, G_all, h_all, *args)
    else:
        x, y, z_all, status, iters, _ = _solve_canonical(lib, P, q, A, b, G_all, h_all, *args)
    zero = q.new_zeros(B, n)
    has_lb, has_ub = lb is not None, ub is not None
    z = z_all if not (has_lb or has_ub) else z_all[:, :m]
    z_lb = z_all[:, m : m + n] if has_lb else zero
    z_ub = z_all[:, m + n * has_lb :] if has_ub else zero
    if low:
        x, y, z, z_lb, z_ub = (t.to(dtype) for t in (x, y, z, z_lb, z_ub))
        z_r = torch.cat([z] + ([z_lb] if has_lb else []) + ([z_ub] if has_ub else []), 1)
        status = _recheck_rounded(status, P, q, A, b, G_all, h_all, x, y, z_r, user_tol, dtype)
    return QPSolution(x, y, z, z_lb, z_ub, status, iters)


def _lift_rounded_psd(P: Tensor, dtype: torch.dtype) -> Tensor:
    """float64 copy of a `dtype` P whose only negative eigenvalue is rounding (λ_min ≥ −64 eps(dtype) max|λ|)
    with λ_min lifted to 0; others as they are. Why: a PSD product such as JᵀJ of rank < n, rounded to float32, has
    λ_min ~ −1e-8 max|λ|, below the float64 convexity test's −1e-9 (NON_CONVEX on most such instances otherwise);
    the lift is within the data's own rounding."""
    S = 0.5 * (P + P.mT)
    _, info = torch.linalg.cholesky_ex(S.detach())
    bad = (info != 0).nonzero().squeeze(-1)
    if not bad.numel():
        return P
    lam = torch.linalg.eigvalsh(S.detach().index_select(0, bad))
    low = lam[:, 0]
    lift = torch.where((low < 0) & (low >= -64.0 * torch.finfo(dtype).eps * lam.abs().amax(-1)), -low, 0.0)
    eye = torch.eye(P.shape[-1], dtype=P.dtype, device=P.device)
    return P.index_add(0, bad, lift[:, None, None] * eye)


def _recheck_rounded(status: Tensor, P: Tensor, q: Tensor, A: Tensor, b: Tensor, G_all: Tensor, h_all: Tensor,
                     x: Tensor, y: Tensor, z_all: Tensor, tol: float, dtype: torch.dtype) -> Tensor:
    """SOLVED instances whose answer, rounded to `dtype`, misses tol on the data rounded alike → TOLERANCE_NOT_MET."""
    solved = status == QPStatus.SOLVED
    if not bool(solved.any()):
        return status
    P_r, q_r, A_r, b_r, G_r, h_r = (t.to(dtype).double() for t in (P, q, A, b, G_all, h_all))
    live = h_r.abs() < 1e20
    G_r = torch.where(live.unsqueeze(-1), G_r, 0.0)
    h_r = torch.where(live, h_r, 1.0)
    ok = kkt_certified(0.5 * (P_r + P_r.mT), q_r, A_r, b_r, G_r, h_r, x.double(), y.double(), z_all.double(), tol)
    return torch.where(solved & ~ok, int(QPStatus.TOLERANCE_NOT_MET), status)
