"""The few array operations whose spelling differs between numpy and torch, so the controller's math has one code path.

`A3CQPController.step` evaluates the tasks, limits and torque law on numpy views of CPU tensors: for these tiny
float64 arrays a numpy op costs ~0.5-1.5 µs against ~2-5 µs for torch (and torch.bmm on 64 stacked 6×7 matrices
~40 µs against ~10), and a step is a few hundred ops. Elsewhere (other devices, `build_context` called with tensors,
autograd) the same code runs on torch tensors. Everything else the code uses (operators, `.mT`, `[..., None]`,
`.sum(-1)`, `xp.where` ...) is spelled the same in both.
"""

from __future__ import annotations

from typing import Union

import numpy as np
import torch

__all__ = ["Array", "xp_of", "mv", "mm", "cat", "const", "zeros", "inv", "solve_spd", "SMALL_BATCH"]

Array = Union[np.ndarray, torch.Tensor]

SMALL_BATCH = 16
"""Up to this batch size the 6×6 / 7×7 inverses and solves go through numpy's LAPACK loop (~8 µs at B = 1 against
~30 µs for torch.linalg); above it torch's batched kernels are faster (B = 64: ~50 µs against ~110)."""


def xp_of(x: Array):  # noqa: ANN201
    """The array module (numpy or torch) of x."""
    return np if isinstance(x, np.ndarray) else torch


def mv(M: Array, v: Array) -> Array:
    """M v for a batch: M [B, m, k], v [B, k] -> [B, m]."""
    if isinstance(M, np.ndarray):
        return np.matmul(M, v[..., None])[..., 0]
    # torch.bmm, not @: on [B, m, k] tensors matmul's broadcasting logic costs ~3 µs per call, more than the product
    return torch.bmm(M, v.unsqueeze(-1)).squeeze(-1)


def mm(A: Array, B: Array) -> Array:
    """Batched matrix product A [B, m, k] @ B [B, k, n] (torch.bmm for tensors, see `mv`)."""
    if isinstance(A, np.ndarray):
        return np.matmul(A, B)
    return torch.bmm(A, B) if A.dim() == 3 and B.dim() == 3 else A @ B


def cat(arrays: list[Array], axis: int) -> Array:
    """Concatenate along `axis`."""
    if isinstance(arrays[0], np.ndarray):
        return np.concatenate(arrays, axis=axis)
    return torch.cat(arrays, dim=axis)


def const(t: torch.Tensor, like: Array) -> Array:
    """A float64 CPU constant tensor in like's kind: a numpy view (no copy) or a tensor of like's dtype/device."""
    if isinstance(like, np.ndarray):
        return t.numpy()
    return t if t.dtype == like.dtype and t.device == like.device else t.to(like)


def zeros(shape: tuple[int, ...], like: Array) -> Array:
    """Zeros of like's kind, dtype and device."""
    return np.zeros(shape) if isinstance(like, np.ndarray) else like.new_zeros(shape)


def inv(M: Array) -> Array:
    """Batched inverse of [B, k, k] matrices (no error check: callers damp them; a singular one gives non-finite
    entries, which the controller's output check turns into the fallback)."""
    if isinstance(M, np.ndarray):
        if M.shape[0] <= SMALL_BATCH:
            try:
                return np.linalg.inv(M)
            except np.linalg.LinAlgError:  # exactly singular: non-finite like torch's inv_ex, not an exception
                pass
        return torch.linalg.inv_ex(torch.from_numpy(M))[0].numpy()
    return torch.linalg.inv_ex(M)[0]


def solve_spd(M: Array, R: Array) -> Array:
    """M⁻¹ R for symmetric positive-definite M [B, k, k] and R [B, k, r] (M not positive definite: non-finite or
    meaningless rows, as with an unchecked Cholesky; the controller's output check catches the non-finite ones)."""
    if isinstance(M, np.ndarray):
        if M.shape[0] <= SMALL_BATCH:
            try:
                return np.linalg.solve(M, R)
            except np.linalg.LinAlgError:
                pass
        L, _ = torch.linalg.cholesky_ex(torch.from_numpy(M))
        return torch.cholesky_solve(torch.from_numpy(np.ascontiguousarray(R)), L).numpy()
    L, _ = torch.linalg.cholesky_ex(M)
    return torch.cholesky_solve(R, L)
