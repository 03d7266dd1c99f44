"""Eq. 26, 29 and 30 against hand computations; batching over any shape; NaN rejection."""

import math

import pytest
import torch

from a3cqp_rl.adaptation import integrate_force, integrate_weights, observe, reward

D = torch.float64


def t(*v):
    return torch.tensor(v, dtype=D)


def test_observe_hand_computed_and_clipped():
    s = observe(t(-0.25, 2.0), t(15.0, -60.0), t(-3.0, 0.0))
    assert torch.allclose(s, t(0.25, 0.5, 0.2, 1.0, 1.0, 0.0).reshape(2, 3))
    s = observe(t(0.5), t(10.0), t(10.0), e_max=2.0, f_env_max=20.0, f_ope_max=40.0)
    assert torch.allclose(s, t(0.25, 0.5, 0.25).unsqueeze(0))


def test_integrate_weights_eq29():
    w_logits, w = integrate_weights(t(0.0, 1.0, -2.9), t(1.0, -0.5, -1.0), sigma_w=6.0, dt=0.01)
    # 0 + 6*0.01*1 = 0.06; 1 - 0.03 = 0.97; -2.9 - 0.06 = -2.96 -> clipped at -3? no: -2.96 > -3
    assert torch.allclose(w_logits, t(0.06, 0.97, -2.96))
    ex = [math.exp(v) for v in (0.06, 0.97, -2.96)]
    assert torch.allclose(w, t(*[v / sum(ex) for v in ex]))
    # saturation at ±σw/2 and rate clipping to [-1, 1]
    w_logits, w = integrate_weights(t(2.99, -2.99, 0.0), t(5.0, -5.0, 0.0))
    assert torch.allclose(w_logits, t(3.0, -3.0, 0.0))
    assert torch.allclose(w.sum(-1), torch.ones((), dtype=D))


def test_integrate_force_eq29d():
    f = integrate_force(t(0.0, 10.0, 19.95, 0.05), t(0.5, 1.0, 1.0, -1.0))
    assert torch.allclose(f, t(0.05, 10.1, 20.0, 0.0))
    assert torch.allclose(integrate_force(t(1.0), t(7.0), sigma_f=10.0, dt=0.01), t(1.1))  # rate clipped to 1


def test_reward_eq30_hand_computed():
    # -0.5*0.2 - 20*(3/15) + 2*(12/30) - 1*(5/20) = -0.1 - 4 + 0.8 - 0.25
    r = reward(t(-0.2), t(12.0), t(3.0), t(5.0))
    assert torch.allclose(r, t(-3.55))
    # normalised terms are clipped to [0, 1]: huge forces saturate
    r = reward(t(0.0), t(300.0), t(0.0), t(0.0))
    assert torch.allclose(r, t(2.0))
    r = reward(t(5.0), t(0.0), t(100.0), t(40.0), alpha=(1, 1, 1, 1))
    assert torch.allclose(r, t(-3.0))


def test_batched_over_any_leading_shape():
    g = torch.Generator().manual_seed(0)
    e, fe, fo, fd = (torch.randn(2, 5, 7, generator=g, dtype=D) for _ in range(4))
    assert observe(e, fe, fo).shape == (2, 5, 7, 3)
    assert reward(e, fe, fo, fd.abs()).shape == (2, 5, 7)
    wl, w = integrate_weights(torch.zeros(2, 5, 3, dtype=D), torch.randn(2, 5, 3, generator=g, dtype=D))
    assert wl.shape == w.shape == (2, 5, 3)
    # batched result equals element-wise result
    r = reward(e, fe, fo, fd.abs())
    assert torch.allclose(r[1, 3, 2], reward(e[1, 3, 2], fe[1, 3, 2], fo[1, 3, 2], fd.abs()[1, 3, 2]))


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_nan_and_inf_name_the_argument(bad):
    with pytest.raises(ValueError, match="f_env"):
        observe(t(0.1), t(bad), t(0.0))
    with pytest.raises(ValueError, match="w_rate"):
        integrate_weights(t(0.0, 0.0, 0.0), t(0.0, bad, 0.0))
    with pytest.raises(ValueError, match="f_d"):
        integrate_force(t(bad), t(0.0))
    with pytest.raises(ValueError, match="f_ope"):
        reward(t(0.0), t(0.0), t(bad), t(0.0))


def test_weight_shape_checked():
    with pytest.raises(ValueError, match="last dim of 3"):
        integrate_weights(torch.zeros(4, dtype=D), torch.zeros(4, dtype=D))
