"""One A2C iteration on the point-mass surrogate in C (`a2c_iteration.c`, built at install time), via ctypes.

Why native: at the paper's settings (4 envs, n = 4) an iteration is ~0.6 M multiply-adds, but the compiled torch
graph spends most of its ~0.4 ms in fixed costs: 26 tiny GEMM calls, 30 kernels, and the dynamo/AOT wrappers
that flatten the state dicts on every call. The C file does the same arithmetic (rollout with auto-reset, n-step
returns or GAE, eq. 31 gradients by hand, λζ clipping, eq. 32) in one call, in the order of the torch reference,
which stays the definition: tests/test_a2c_native.py checks 60 iterations in lockstep against `fused_iteration`
(three network/option sets) and the first update of whole runs against the torch trainer. Results agree to float32 round-off, not bit for bit (MKL sums in its own order);
each path is deterministic on its own.

`NativeIteration.run` runs many iterations in one call (`a2c_iterations`): `a2c.train` returns to Python only at log
rows, checkpoints, updates inside the `average_last` window and episode ends (new episodes are drawn by the env's
torch generator), so at n = 1 (250,000 updates per 1e6 steps) the loop is not bound by Python per update. It adds
each rollout's rewards to the running episode returns in the order torch's `rewards.sum(0)` adds them (checked for
the trainer's shape when it is built; other shapes keep one call per iteration): the results are bit for bit those
of one call per iteration (tests/test_a2c_chunked.py, also against numbers stored before the change).

`FusedRollout` takes it when `a2c.backend` allows (`auto`: PointMassEnv on the CPU and at most
`AUTO_MAX_BATCH` samples per update, where it is faster; bigger batches are GEMM-bound, where MKL wins).
`A3CQP_NATIVE_A2C=0` switches it off; a library not built at install time (no compiler) or stale logs one warning and the torch path runs.
"""

from __future__ import annotations

import ctypes
import logging
from pathlib import Path

import torch
from torch import Tensor

from a3cqp_rl.config import ExperimentConfig
from a3cqp_rl.native_build import LazyLibrary
from envs.native import HEADER, PMParams, pm_params
from envs.native import unsupported as env_unsupported

__all__ = ["Params", "NativeIteration", "load", "unsupported", "SOURCE", "AUTO_MAX_BATCH", "MAX_DEPTH"]

SOURCE = Path(__file__).with_name("a2c_iteration.c")
MAX_DEPTH = 8
AUTO_MAX_BATCH = 512
"""`backend: auto` uses C up to this many samples per update (n_steps × num_envs). Measured (fd config, 16 steps):
16 envs C 123k vs torch 50k steps/s; 64 envs 98k vs 110k; 256 envs 109k vs 133k (torch after a 15-35 s compile)."""

_log = logging.getLogger(__name__)
_i, _d = ctypes.c_int64, ctypes.c_double


class Params(ctypes.Structure):
    """`a2c_params` of a2c_iteration.c, field by field."""

    _fields_ = [("env", PMParams), ("n", _i),
                ("obs_dim", _i), ("act_dim", _i), ("critic_dim", _i), ("privileged", _i), ("shared", _i),
                ("depth", _i), ("hidden", _i * MAX_DEPTH), ("size", _i),
                ("off_w", (_i * MAX_DEPTH) * 2), ("off_b", (_i * MAX_DEPTH) * 2), ("off_pi_w", _i), ("off_pi_b", _i),
                ("off_vf_w", _i), ("off_vf_b", _i), ("off_log_std", _i), ("in_dim", _i * 2),
                ("gae", _i), ("normalize_advantage", _i),
                ("gamma", _d), ("gae_lambda", _d), ("vf_coef", _d), ("ent_coef", _d), ("bound_coef", _d),
                ("max_grad_norm", _d), ("lr", _d), ("rms_alpha", _d), ("rms_eps", _d)]


STATE = ("x", "x_dot", "target", "w_logits", "f_d", "wall_pos", "has_wall", "t", "f_env", "f_ope", "scenario", "slot")
PENDING = ("target", "wall_pos", "has_wall", "scenario", "w_logits", "f_d")
"""The pointer table's order (the B_* enum of the C file): STATE, PENDING, then schedule, noise, flat, square_avg,
metrics, rewards, dones, workspace."""
_NOISE = len(STATE) + len(PENDING) + 1
_BUFFERS = len(STATE) + len(PENDING) + 8
_DTYPES = {"has_wall": torch.bool, "t": torch.int64, "scenario": torch.int64, "slot": torch.int64}


def _bind(path: Path) -> ctypes.CDLL:
    """Load the compiled library and declare its functions (checking the C layout against Params)."""
    lib = ctypes.CDLL(str(path))
    lib.a2c_params_size.restype = lib.a2c_workspace_floats.restype = lib.a2c_buffer_count.restype = ctypes.c_int64
    if lib.a2c_params_size() != ctypes.sizeof(Params):
        raise RuntimeError("a2c_params in a2c_iteration.c and native.Params differ")
    if lib.a2c_buffer_count() != _BUFFERS:
        raise RuntimeError("the pointer table of a2c_iteration.c and native.STATE/PENDING differ")
    lib.a2c_workspace_floats.argtypes = [ctypes.c_void_p]
    lib.a2c_iteration.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
    lib.a2c_iteration.restype = ctypes.c_int64
    lib.a2c_iterations.argtypes = [ctypes.c_void_p, ctypes.c_void_p, ctypes.c_int64, ctypes.c_void_p, ctypes.c_void_p,
                                   ctypes.c_void_p]
    lib.a2c_iterations.restype = ctypes.c_int64
    lib.a2c_outer_sum.argtypes = [ctypes.c_void_p, ctypes.c_int64, ctypes.c_int64, ctypes.c_void_p]
    lib.a2c_outer_sum.restype = None
    return lib


_library = LazyLibrary(SOURCE, "A3CQP_NATIVE_A2C", _bind, _log, "algorithms: native A2C iteration", "the torch path",
                       depends=(HEADER,))


def load() -> ctypes.CDLL | None:
    """The compiled library, or None (A3CQP_NATIVE_A2C=0, or not built / stale: one warning)."""
    return _library.get()


def unsupported(env, layout) -> str | None:  # noqa: ANN001
    """Why the C iteration cannot run this trainer (None when it can)."""
    from envs.point_mass import PointMassEnv

    if type(env) is not PointMassEnv:
        return f"the C iteration simulates PointMassEnv only, not {type(env).__name__}"
    if env.device.type != "cpu":
        return f"the C iteration runs on the CPU, the env is on {env.device}"
    if len(layout.hidden) > MAX_DEPTH or layout.act_dim != 4 or layout.obs_dim != 3:
        return f"network {layout.hidden} with {layout.obs_dim} -> {layout.act_dim} is outside the C file's limits"
    return env_unsupported(ExperimentConfig(point_mass=env.cfg, adaptation=env.adapt, reward=env.rew))


def _params(env, layout, hp) -> Params:  # noqa: ANN001
    cfg = ExperimentConfig(point_mass=env.cfg, adaptation=env.adapt, reward=env.rew)
    p = Params(env=pm_params(cfg, env.num_envs), n=hp.n_steps, obs_dim=layout.obs_dim, act_dim=layout.act_dim,
               critic_dim=layout.critic_obs_dim, privileged=int(layout.critic_obs_dim > layout.obs_dim),
               shared=int(layout.network == "shared"), depth=len(layout.hidden), size=layout.size,
               gae=int(hp.gae_lambda != 1.0), normalize_advantage=int(hp.normalize_advantage),
               gamma=hp.gamma, gae_lambda=hp.gae_lambda, vf_coef=hp.vf_coef, ent_coef=hp.ent_coef,
               bound_coef=hp.bound_coef, max_grad_norm=hp.max_grad_norm, lr=hp.learning_rate, rms_alpha=hp.rms_alpha,
               rms_eps=hp.rms_eps)
    for k, h in enumerate(layout.hidden):
        p.hidden[k] = h
    stacks = ("pi", "vf") if layout.network == "separate" else ("trunk",)
    for st, name in enumerate(stacks):
        p.in_dim[st] = layout.in_dims[name]
        for k in range(len(layout.hidden)):
            p.off_w[st][k], p.off_b[st][k] = layout.offsets[f"{name}.{k}.w"][0], layout.offsets[f"{name}.{k}.b"][0]
    p.off_pi_w, p.off_pi_b = layout.offsets["pi.out.w"][0], layout.offsets["pi.out.b"][0]
    p.off_vf_w, p.off_vf_b = layout.offsets["vf.out.w"][0], layout.offsets["vf.out.b"][0]
    p.off_log_std = layout.offsets["log_std"][0]
    return p


class NativeIteration:
    """`fused_iteration` in C: same call and results (to float32 round-off); the env state is updated in place."""

    def __init__(self, lib: ctypes.CDLL, env, layout, hp) -> None:  # noqa: ANN001
        """Bind `lib` to `env` (a PointMassEnv), the network `layout` and the A2C settings `hp`."""
        why = unsupported(env, layout)
        if why:
            raise ValueError(why)
        self.lib, self.params = lib, _params(env, layout, hp)
        N, n = env.num_envs, hp.n_steps
        self.work = torch.empty(int(lib.a2c_workspace_floats(ctypes.byref(self.params))), dtype=torch.float32)
        self.metrics = torch.empty(5, dtype=torch.float32)
        self.rewards = torch.empty(n, N, dtype=torch.float32)
        self.dones = torch.empty(n, N, dtype=torch.bool)
        self.table = (ctypes.c_void_p * _BUFFERS)()
        self._shapes = {k: (N, 3) if k == "w_logits" else (N,) for k in STATE}
        self._seen: tuple | None = None
        self.done_count = 0
        """Episode ends (dones) in the last call's rollout."""
        self._noise_shape = torch.Size((n, N, layout.act_dim))
        self._params_ref = ctypes.byref(self.params)

    def _check(self, flat: Tensor, square_avg: Tensor, state: dict, pending: dict, schedule: Tensor) -> None:
        p = self.params
        for group, d in (("state", state), ("pending", pending)):
            for k in STATE if group == "state" else PENDING:
                v = d[k]
                if v.dtype != _DTYPES.get(k, torch.float64) or tuple(v.shape) != self._shapes[k] or not v.is_contiguous():
                    raise ValueError(f"{group}[{k!r}] must be a contiguous {_DTYPES.get(k, torch.float64)} tensor of "
                                     f"shape {self._shapes[k]}, got {v.dtype} {tuple(v.shape)}")
        want = {"schedule": ((2, p.env.N, p.env.sched_len), torch.float64, schedule), "flat": ((p.size,), torch.float32, flat),
                "square_avg": ((p.size,), torch.float32, square_avg)}
        for name, (shape, dtype, v) in want.items():
            if tuple(v.shape) != shape or v.dtype != dtype or not v.is_contiguous():
                raise ValueError(f"{name} must be a contiguous {dtype} tensor of shape {shape}, got {v.dtype} {tuple(v.shape)}")

    def __call__(self, flat: Tensor, square_avg: Tensor, state: dict, pending: dict, schedule: Tensor,
                 noise: Tensor) -> tuple[dict, Tensor, Tensor, Tensor]:
        """One iteration: (state (the same dict, updated in place), metrics [5], rewards [n, N], dones [n, N]).

        `flat` and `square_avg` are updated in place. The three outputs are this object's buffers: valid until the
        next call.
        """
        if noise.shape != self._noise_shape or noise.dtype != torch.float32 or not noise.is_contiguous():
            raise ValueError(f"noise must be a contiguous float32 tensor of shape {tuple(self._noise_shape)}, "
                             f"got {noise.dtype} {tuple(noise.shape)}")
        self._bind_tensors(flat, square_avg, state, pending, schedule, noise)
        self.done_count = self.lib.a2c_iteration(self._params_ref, self.table)
        return state, self.metrics, self.rewards, self.dones

    def run(self, count: int, flat: Tensor, square_avg: Tensor, state: dict, pending: dict, schedule: Tensor,
            noise: Tensor, metric_sum: Tensor, ep_return: Tensor, ep_length: Tensor) -> int:
        """`count` iterations in one C call, noise [count·n, N, act]: each adds its metrics to `metric_sum` [5], and
        each but the last its rollout's reward sums to `ep_return` [N] (float32) and n to `ep_length` [N] (int64), as
        per-iteration calls and `FusedRollout.iterate` would; the last one's metrics, rewards and dones stay in this
        object's buffers, `done_count` its episode ends. Returns the iterations run: fewer than `count` only when an
        episode ended before the last (the caller's noise is then used up to that point only)."""
        n, N, A = self._noise_shape
        if tuple(noise.shape) != (count * n, N, A) or noise.dtype != torch.float32 or not noise.is_contiguous():
            raise ValueError(f"noise must be a contiguous float32 tensor of shape {(count * n, N, A)}, "
                             f"got {noise.dtype} {tuple(noise.shape)}")
        for name, t, shape, dtype in (("metric_sum", metric_sum, (5,), torch.float32),
                                      ("ep_return", ep_return, (N,), torch.float32),
                                      ("ep_length", ep_length, (N,), torch.int64)):
            if tuple(t.shape) != shape or t.dtype != dtype or not t.is_contiguous():
                raise ValueError(f"{name} must be a contiguous {dtype} tensor of shape {shape}, got {t.dtype} {tuple(t.shape)}")
        self._bind_tensors(flat, square_avg, state, pending, schedule, noise)
        done = self.lib.a2c_iterations(self._params_ref, self.table, count, metric_sum.data_ptr(), ep_return.data_ptr(),
                                       ep_length.data_ptr())
        self.done_count = int(self.dones.sum()) if done else 0
        return int(done)

    def sums_like_torch(self) -> bool:
        """Whether `run` adds each rollout's rewards [n, N] as torch's `rewards.sum(0)` does (see `outer_sum_matches_torch`)."""
        n, N, _ = self._noise_shape
        return outer_sum_matches_torch(self.lib, n, N)

    def _bind_tensors(self, flat: Tensor, square_avg: Tensor, state: dict, pending: dict, schedule: Tensor,
                      noise: Tensor) -> None:
        seen = self._seen
        # The env swaps its state dicts only on reset/resume (and edits their tensors in place): check layouts and
        # take addresses then, not on every call (holding the objects, so their addresses stay theirs).
        if seen is None or state is not seen[0] or pending is not seen[1] or schedule is not seen[2] \
                or flat is not seen[3] or square_avg is not seen[4]:
            self._check(flat, square_avg, state, pending, schedule)
            tensors = [*(state[k] for k in STATE), *(pending[k] for k in PENDING), schedule, noise, flat, square_avg,
                       self.metrics, self.rewards, self.dones, self.work]
            for k, t in enumerate(tensors):
                self.table[k] = t.data_ptr()
            self._seen = (state, pending, schedule, flat, square_avg)
        self.table[_NOISE] = noise.data_ptr()


def outer_sum_matches_torch(lib: ctypes.CDLL, rows: int, cols: int, trials: int = 64) -> bool:
    """Whether a2c_outer_sum adds [rows, cols] float32 blocks bit for bit as torch's `x.sum(0)` does (random blocks
    whose entries span ~20 binary orders, where any other order of the additions shows)."""
    gen = torch.Generator().manual_seed(0)
    out = torch.empty(cols, dtype=torch.float32)
    for _ in range(trials):
        x = (torch.randn(rows, cols, generator=gen) * torch.exp2(torch.randint(-10, 10, (rows, cols), generator=gen))).float()
        lib.a2c_outer_sum(x.data_ptr(), rows, cols, out.data_ptr())
        if not torch.equal(out, x.sum(0)):
            return False
    return True
