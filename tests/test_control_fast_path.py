"""The fast control path: MuJoCo-sourced site kinematics (SimState.kin) give the same controller as PandaModel's."""

from __future__ import annotations

import torch

from a3cqp_rl.control import A3CQPController
from a3cqp_rl.robot import PandaModel, PandaSim

F64 = torch.float64


def test_sim_kinematics_match_the_torch_model_on_a_moving_arm() -> None:
    sim, model = PandaSim(3), PandaModel()
    gen = torch.Generator().manual_seed(0)
    s = sim.observe()
    for _ in range(150):  # random torques around gravity compensation: a fast, non-trivial motion
        sim.step(s.bias + 8.0 * torch.randn(3, 7, generator=gen, dtype=F64))
        s = sim.observe()
    assert float(s.qd.abs().max()) > 0.5
    ref = model.kinematics(s.q, s.qd)
    for name, atol in (("pos", 1e-7), ("rot", 1e-9), ("jac", 1e-7), ("jdot_qdot", 1e-7), ("twist", 1e-7)):
        torch.testing.assert_close(getattr(s.kin, name), getattr(ref, name), atol=atol, rtol=0.0, msg=name)
    assert PandaSim(1, control_site=None).observe().kin is None


def test_controller_with_sim_kinematics_equals_controller_with_model_kinematics() -> None:
    """Two controllers, one fed SimState.kin and one computing PandaModel.kinematics, on the same states."""
    n = 2
    sim = PandaSim(n)
    fast, ref = A3CQPController(n), A3CQPController(n)
    gen = torch.Generator().manual_seed(1)
    s = sim.observe()
    pos0, rot0 = ref.model.fk(s.q.clone())
    pos_d = pos0 + 0.1 * (torch.rand(n, 3, generator=gen, dtype=F64) - 0.5)
    for k in range(120):
        if k % 20 == 0:
            w = torch.softmax(6.0 * (torch.rand(n, 6, 3, generator=gen, dtype=F64) - 0.5), -1)
            f_d = 10.0 * torch.rand(n, 6, generator=gen, dtype=F64)
        a = fast.step(s.q, s.qd, s.mass, s.bias, w, f_d, pos_d, rot0, f_env=s.f_env, kin=s.kin)
        b = ref.step(s.q, s.qd, s.mass, s.bias, w, f_d, pos_d, rot0, f_env=s.f_env)
        torch.testing.assert_close(a.tau, b.tau, atol=1e-5, rtol=1e-6)
        torch.testing.assert_close(a.pose_error, b.pose_error, atol=1e-7, rtol=0.0)
        sim.step(a.tau)
        s = sim.observe()
    assert not bool(a.fallback.any())
