"""Eq. 32 RMSProp (ε inside the root) against hand computation and against torch.optim.RMSprop."""

import math

import pytest
import torch

from algorithms.rmsprop import RMSpropEq32, clip_grad_norm_


def test_two_steps_by_hand():
    p = torch.nn.Parameter(torch.tensor([1.0, -2.0], dtype=torch.float64))
    opt = RMSpropEq32([p], lr=0.1, alpha=0.9, eps=0.01, init_square_avg=0.0)
    g1 = torch.tensor([0.5, -1.0], dtype=torch.float64)
    p.grad = g1.clone()
    opt.step()
    s1 = 0.1 * g1**2
    expect1 = torch.tensor([1.0, -2.0], dtype=torch.float64) - 0.1 * g1 / torch.sqrt(s1 + 0.01)
    assert torch.allclose(p.detach(), expect1)
    g2 = torch.tensor([0.25, 3.0], dtype=torch.float64)
    p.grad = g2.clone()
    opt.step()
    s2 = 0.9 * s1 + 0.1 * g2**2
    assert torch.allclose(p.detach(), expect1 - 0.1 * g2 / torch.sqrt(s2 + 0.01))


def test_tf_like_accumulator_starts_at_one():
    p = torch.nn.Parameter(torch.tensor([0.0]))
    opt = RMSpropEq32([p], lr=1.0, alpha=0.99, eps=1e-5, init_square_avg=1.0)
    p.grad = torch.tensor([2.0])
    opt.step()
    assert p.item() == pytest.approx(-2.0 / math.sqrt(0.99 + 0.01 * 4 + 1e-5), rel=1e-6)


def _run_both(grads, ours_eps, torch_eps):
    """Apply `grads` with eq. 32 and with torch.optim.RMSprop from the same start; return both params."""
    a = torch.nn.Parameter(torch.zeros(5, dtype=torch.float64))
    b = torch.nn.Parameter(torch.zeros(5, dtype=torch.float64))
    ours = RMSpropEq32([a], lr=1e-2, alpha=0.99, eps=ours_eps)
    ref = torch.optim.RMSprop([b], lr=1e-2, alpha=0.99, eps=torch_eps)
    for g in grads:
        a.grad, b.grad = g.clone(), g.clone()
        ours.step()
        ref.step()
    return a.detach(), b.detach()


def test_differs_from_torch_rmsprop_only_by_eps_placement():
    torch.manual_seed(0)
    grads = [torch.randn(5, dtype=torch.float64) * 1e-3 for _ in range(3)]
    # eps = 1e-4 inside the root acts like 1e-2 outside it: with tiny gradients the two clearly differ
    a, b = _run_both(grads, ours_eps=1e-4, torch_eps=1e-4)
    assert not torch.allclose(a, b, rtol=1e-2)
    # with a negligible eps (1e-30 inside ~ 1e-15 outside) both agree
    c, d = _run_both(grads, ours_eps=1e-30, torch_eps=1e-15)
    assert torch.allclose(c, d, rtol=1e-8)


def test_global_norm_clipping_matches_torch():
    torch.manual_seed(1)
    gs = [torch.randn(3, 4), torch.randn(7)]
    ref = [g.clone().requires_grad_() for g in gs]
    for r, g in zip(ref, gs):
        r.grad = g.clone()
    norm_ref = torch.nn.utils.clip_grad_norm_(ref, 0.5)
    norm = clip_grad_norm_(gs, 0.5)
    assert torch.allclose(norm, norm_ref)
    for r, g in zip(ref, gs):
        assert torch.allclose(r.grad, g)
    assert torch.linalg.vector_norm(torch.cat([g.reshape(-1) for g in gs])) == pytest.approx(0.5, rel=1e-5)


def test_optimizer_clips_before_step():
    p = torch.nn.Parameter(torch.zeros(2, dtype=torch.float64))
    opt = RMSpropEq32([p], lr=1.0, alpha=0.0, eps=1e-12, max_grad_norm=1.0)
    p.grad = torch.tensor([30.0, 40.0], dtype=torch.float64)  # norm 50 -> clipped to (0.6, 0.8)
    opt.step()
    # with alpha = 0 the step is -g/|g| elementwise = -sign(g)
    assert torch.allclose(p.detach(), torch.tensor([-1.0, -1.0], dtype=torch.float64), atol=1e-6)


@pytest.mark.parametrize("kw", [dict(lr=0), dict(alpha=1.0), dict(eps=0), dict(init_square_avg=-1), dict(max_grad_norm=0)])
def test_bad_hyper_parameters(kw):
    with pytest.raises(ValueError):
        RMSpropEq32([torch.nn.Parameter(torch.zeros(1))], **kw)


def test_a_tensor_learning_rate_steps_like_the_float_one():
    from algorithms.rmsprop import rmsprop_step_

    g = torch.Generator().manual_seed(0)
    p, grad = torch.randn(50, generator=g), torch.randn(50, generator=g)
    a, b = p.clone(), p.clone()
    sa, sb = torch.zeros(50), torch.zeros(50)
    rmsprop_step_([a], [grad], [sa], 1e-2, 0.9, 1e-5)
    rmsprop_step_([b], [grad], [sb], torch.tensor(1e-2), 0.9, 1e-5)
    assert torch.allclose(a, b, rtol=0, atol=1e-7) and not torch.equal(a, p) and torch.equal(sa, sb)
