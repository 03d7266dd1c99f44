"""PandaEnv's control period in one C call (envs/native/tick.py) against the Python period it replaces: bit for bit."""

from __future__ import annotations

import logging

import numpy as np
import pytest
import torch

from a3cqp_rl.config import config_from_dict
from envs.native import tick as tick_mod
from envs.panda import PandaEnv

needs_library = pytest.mark.skipif(tick_mod._library.get() is None, reason="the native tick library is not built")

# contact from the 150th agent period on (the peg on the rim and in the bore)
QUICK_PEG = {"panda": {"peg_in_hole": {"settle_time": 0.1, "approach_time": 0.5, "align_time": 0.5,
                                       "descent_time": 0.3, "time_limit": 6.0}}}

_ATTRS = ("q", "qd", "tau", "pos", "rot", "f_env", "f_env_true", "f_ope", "f_ext", "handle_pos", "handle_force",
          "_r_handle", "_twist", "max_penetration", "joint_limit_excess", "joint_limit_joint", "joint_speed_ratio",
          "fallbacks", "diverged", "t")


def _pair(n: int, overrides: dict | None = None) -> tuple[PandaEnv, PandaEnv]:
    cfg = config_from_dict({**QUICK_PEG, **(overrides or {})})
    c = PandaEnv(n, cfg, seed=0)
    with tick_mod.numpy_tick():
        py = PandaEnv(n, cfg, seed=0)
    assert c._native_tick is not None and py._native_tick is None
    return c, py


def _same(c: PandaEnv, py: PandaEnv, step: int) -> None:
    for name in _ATTRS:
        a, b = getattr(c, name), getattr(py, name)
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), f"{name} differs at agent period {step}"
    for name in ("q_des", "qd_des"):
        assert torch.equal(getattr(c.ctrl, name), getattr(py.ctrl, name)), f"{name} differs at agent period {step}"
    wc, wp = c.ctrl._warm, py.ctrl._warm
    assert np.array_equal(wc._duals(), wp._duals()), f"the QP's warm start differs at agent period {step}"
    assert np.array_equal(wc._np("_x"), wp._np("_x"))


@needs_library
def test_the_c_period_is_the_python_period_bit_for_bit_with_contacts_parked_arms_and_a_divergence(
        caplog, monkeypatch, tmp_path) -> None:  # noqa: ANN001
    monkeypatch.chdir(tmp_path)  # (MuJoCo writes its warnings about the diverging arm to MUJOCO_LOG.TXT)
    n = 14
    c, py = _pair(n)
    gen = torch.Generator().manual_seed(0)
    tds = [c.reset(), py.reset()]
    contact, caplog.handler.level = False, logging.WARNING
    for step in range(300):
        action = torch.rand(n, 6, 4, generator=gen) * 2 - 1
        if step == 100:  # two arms held (every arm computed, the held ones' τ = h + g)
            for env in (c, py):
                env.park(np.array([0, 1]))
        if step == 250:  # twelve held: the controller computes the other two only
            for env in (c, py):
                env.park(np.arange(2, 12))
        if step == 200:  # a diverging arm: the controller's stand-ins (the rest of that period in Python), its reset
            for env in (c, py):
                env.sim.data.qvel[env.sim._dadr[13, 2]] = np.nan
        for i, env in enumerate((c, py)):
            tds[i]["action"] = action
            tds[i] = env.step(tds[i])["next"]
        _same(c, py, step)
        assert torch.equal(tds[0]["observation"], tds[1]["observation"])
        contact |= bool((c.max_penetration > 0).any())
    assert contact
    assert c.diverged[13] and c.parked.sum() == 12
    assert [r.getMessage() for r in caplog.records if "diverged" in r.getMessage()] == 2 * [
        "panda env: robot 13 diverged at t = 2.000 s (non-finite state); its episode ends"]
    periods = c._native_tick.periods
    assert periods["python_controller"] >= 1 and periods["whole"] >= 2990 and periods["python"] <= 1


@needs_library
def test_the_c_period_runs_only_where_every_piece_is_the_common_one() -> None:
    noisy = config_from_dict({**QUICK_PEG, "panda": {**QUICK_PEG["panda"], "sensors": {"ft_force_noise": 0.1}}})
    assert PandaEnv(2, noisy, seed=0)._native_tick is None  # (sensor errors: the Python `_measure`)
    assert PandaEnv(4, config_from_dict(QUICK_PEG), seed=0, sim_threads=2)._native_tick is None  # a sharded sim
    with tick_mod.numpy_tick():
        assert PandaEnv(2, config_from_dict(QUICK_PEG), seed=0)._native_tick is None


@needs_library
def test_mjdata_layout_reads_ncon_and_the_contacts_of_a_live_simulation() -> None:
    import ctypes

    layout = tick_mod._data_layout()
    c, _ = _pair(3)
    td = c.reset()
    for _ in range(200):
        td["action"] = torch.zeros(3, 6, 4)
        td = c.step(td)["next"]
    d = c.sim.data
    assert d.ncon > 0
    ncon = np.frombuffer(ctypes.string_at(d._address + layout["ncon_offset"], 4), dtype=np.int32)[0]
    base = np.frombuffer(ctypes.string_at(d._address + layout["contact_offset"], 8), dtype=np.uint64)[0]
    assert ncon == d.ncon and base == d.contact.dist.__array_interface__["data"][0]
    assert layout["contact_size"] == d.contact.dist.strides[0]


@needs_library
def test_the_c_period_is_the_python_period_bit_for_bit_with_the_operators_hand() -> None:
    n, scene = 3, "guidance"  # (the operator takes the handle after 1.5 s)
    cfg = config_from_dict({"panda": {"operator": {"noise": 0.5}}})
    c = PandaEnv(n, cfg, seed=1, scene=scene)
    with tick_mod.numpy_tick():
        py = PandaEnv(n, cfg, seed=1, scene=scene)
    gen = torch.Generator().manual_seed(1)
    tds = [c.reset(), py.reset()]
    pushed = 0
    for step in range(250):
        action = torch.rand(n, 6, 4, generator=gen) * 2 - 1
        for i, env in enumerate((c, py)):
            tds[i]["action"] = action
            tds[i] = env.step(tds[i])["next"]
        _same(c, py, step)
        pushed += int(c.operator.active.any() and np.abs(c.handle_force).sum() > 0)
    assert pushed > 50 and c._native_tick.periods["whole"] == 2500


def _compile_engine_stop(tmp_path) -> "ctypes.CDLL":  # noqa: ANN001, F821
    """A MuJoCo control callback in C that calls mju_error (an engine error inside mj_step1, without Python)."""
    import ctypes
    import shlex
    import subprocess
    import sysconfig

    src = tmp_path / "stop.c"
    src.write_text('typedef void (*err_fn)(const char*, ...);\nstatic err_fn err;\n'
                   'void stop_set(err_fn f) { err = f; }\n'
                   'void stop_control(const void* m, void* d) { (void)m; (void)d; err("stopped by %s", "the test"); }\n')
    out = tmp_path / "stop.so"
    cc = shlex.split(sysconfig.get_config_var("CC") or "cc")
    subprocess.run([*cc, "-shared", "-fPIC", str(src), "-o", str(out)], check=True)
    lib = ctypes.CDLL(str(out))
    lib.stop_set(ctypes.cast(tick_mod._mujoco_library().mju_error, ctypes.c_void_p))
    return lib


@needs_library
@pytest.mark.parametrize("callback", ["python", "native"])
def test_an_engine_error_inside_the_c_period_raises_as_the_bindings_raise_it(callback, tmp_path) -> None:  # noqa: ANN001
    import ctypes

    import mujoco

    c, py = _pair(2)
    tds = [c.reset(), py.reset()]
    for i, env in enumerate((c, py)):
        tds[i]["action"] = torch.zeros(2, 6, 4)
        tds[i] = env.step(tds[i])["next"]
    calls = []

    def raising(m, d) -> None:  # noqa: ANN001
        calls.append(d.time)
        raise ValueError("the control callback failed")

    if callback == "python":
        expected, hook = (ValueError, "the control callback failed"), raising
    else:
        lib = _compile_engine_stop(tmp_path)
        expected = (mujoco.FatalError, "stopped by the test")
        hook = ctypes.CFUNCTYPE(None, ctypes.c_void_p, ctypes.c_void_p)(("stop_control", lib))
    raised = []
    mujoco.set_mjcb_control(hook)
    try:
        for i, env in enumerate((c, py)):
            tds[i]["action"] = torch.zeros(2, 6, 4)
            with pytest.raises(expected[0]) as info:
                env.step(tds[i])
            raised.append(str(info.value))
    finally:
        mujoco.set_mjcb_control(None)
    assert raised == [expected[1], expected[1]]
    assert callback == "native" or len(calls) == 2  # (the first mj_step1 of each env's agent period)
    assert c._native_tick.periods["whole"] == 10
    # the call put MuJoCo's error routing back as it found it (none on this thread)
    mj = tick_mod._mujoco_library()
    mj._mjPRIVATE_setTlsLogHandler.restype = ctypes.c_void_p
    assert mj._mjPRIVATE_setTlsLogHandler(None) is None
    # and the next agent period runs
    for i, env in enumerate((c, py)):
        tds[i]["action"] = torch.zeros(2, 6, 4)
        env.step(tds[i])
    assert np.isfinite(c.q).all() and c._native_tick.periods["whole"] == 20
