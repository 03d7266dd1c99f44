"""A3CQPController.step(active=): robots left out of a step hold with h + g, and the others compute the same numbers
as in a step of all (the evaluation's finished arms waiting for the rest of their batch)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

import a3cqp_rl.control.controller as controller_module
from a3cqp_rl.control import A3CQPController, ControllerOptions, native
from a3cqp_rl.control.exceptions import ControlShapeError
from a3cqp_rl.robot import PANDA_LIMITS
from tests.test_control_native import random_inputs

N = 12
FIELDS = ("tau", "qdd", "wrench", "qdd_pd", "pose_error", "f_adm", "f_ctc", "status", "fallback", "saturated",
          "iterations")


def _inputs(seed: int) -> dict:
    inputs, _ = random_inputs(N, seed)
    return inputs


def _run(ctrl: A3CQPController, steps: list[dict], active: list[torch.Tensor | None]) -> list:
    outs = []
    for inp, act in zip(steps, active):
        outs.append((ctrl.step(**inp, active=act), ctrl.q_des.clone(), ctrl.qd_des.clone()))
    return outs


@pytest.mark.parametrize("backend,subset", [("native", True), ("native", False), ("python", False)])
def test_active_robots_compute_what_a_step_of_all_does(backend: str, subset: bool,
                                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """Five steps, robots 3, 7 and 8 left out of the last three: the others' outputs and references equal a run of
    all robots bit for bit (QP warm starts included); the idle ones get h + g and keep q*, q̇*. `subset`: the C route
    computes the active robots alone (else all, the idle ones held after: below SUBSET_MIN_IDLE idle robots)."""
    if backend == "native" and native.load() is None:
        pytest.skip("no C compiler: the native step is not built")
    monkeypatch.setattr(controller_module, "SUBSET_MIN_IDLE", 1 if subset else N + 1)
    steps = [_inputs(s) for s in range(5)]
    idle = np.array([3, 7, 8])
    mask = torch.ones(N, dtype=torch.bool)
    mask[idle] = False
    opts = ControllerOptions(backend=backend)
    first = _inputs(99)
    every, some = (A3CQPController(N, options=opts) for _ in range(2))
    for c in (every, some):
        c.reset(first["q"], first["qd"])
    ref = _run(every, steps, [None] * 5)
    got = _run(some, steps, [None, None, mask, mask, mask])
    live = np.setdiff1d(np.arange(N), idle)
    for k in range(5):
        (o_ref, qd_ref, qdd_ref), (o, qd_, qdd_) = ref[k], got[k]
        rows = np.arange(N) if k < 2 else live
        for name in FIELDS:
            assert torch.equal(getattr(o, name)[rows], getattr(o_ref, name)[rows]), (k, name)
        assert torch.equal(qd_[rows], qd_ref[rows]) and torch.equal(qdd_[rows], qdd_ref[rows])
    held_q, held_qd = got[1][1][idle], got[1][2][idle]
    tau_max = PANDA_LIMITS.tensors()["tau_max"].to(torch.float64)
    for k in range(2, 5):
        o, q_des, qd_des = got[k]
        assert torch.equal(q_des[idle], held_q) and torch.equal(qd_des[idle], held_qd)
        assert torch.equal(o.tau[idle], steps[k]["bias"][idle].clip(-tau_max, tau_max))
        assert not o.fallback[idle].any() and (o.status[idle] == 0).all() and not o.saturated[idle].any()
        assert (o.qdd[idle] == 0).all() and (o.wrench[idle] == 0).all()
    # back in: robot 3 computes from its kept references (not what it would have without the pause)
    back = some.step(**_inputs(5), active=None)
    assert torch.isfinite(back.tau).all()


def test_all_active_is_a_plain_step_and_bad_masks_are_refused() -> None:
    """An all-True mask is a step of all; a mask of another shape or dtype is a one-line error."""
    inp = _inputs(0)
    a, b = A3CQPController(N), A3CQPController(N)
    oa, ob = a.step(**inp), b.step(**inp, active=torch.ones(N, dtype=torch.bool))
    assert all(torch.equal(getattr(oa, f), getattr(ob, f)) for f in FIELDS)
    with pytest.raises(ControlShapeError, match="active must be a bool"):
        a.step(**inp, active=torch.ones(N - 1, dtype=torch.bool))
    with pytest.raises(ControlShapeError, match="active must be a bool"):
        a.step(**inp, active=torch.ones(N))
