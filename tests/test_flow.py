"""flow.py against closed-form answers."""
import math

import torch

import flow


def test_interpolate_endpoints_and_midpoint():
    x0, x1 = torch.randn(3, 4), torch.randn(3, 4)
    assert torch.equal(flow.interpolate(x0, x1, torch.zeros(3)), x0)   # t = 0 is noise
    assert torch.equal(flow.interpolate(x0, x1, torch.ones(3)), x1)    # t = 1 is data
    assert torch.allclose(flow.interpolate(x0, x1, torch.full((3,), 0.5)), (x0 + x1) / 2)


def test_euler_is_exact_on_a_constant_field():
    x0, d = torch.randn(5, 2), torch.randn(5, 2)
    xs, ts = flow.sample_ode(lambda x, t: d, x0, steps=7, return_trajectory=True)
    assert xs.shape == (8, 5, 2) and ts.shape == (8,)
    for k in range(8):
        assert torch.allclose(xs[k], x0 + ts[k] * d, atol=1e-6)


def test_euler_on_a_linear_field_matches_its_closed_form_and_converges():
    # dx/dt = a x: Euler with N steps gives x0 (1 + a/N)^N exactly; the ODE's solution is x0 e^a
    a, x0 = -1.3, torch.randn(10, 3)
    for n in (1, 4, 50):
        x1 = flow.sample_ode(lambda x, t: a * x, x0, steps=n)
        assert torch.allclose(x1, x0 * (1 + a / n) ** n, atol=1e-5)
    err = (flow.sample_ode(lambda x, t: a * x, x0, steps=2000) - x0 * math.exp(a)).abs().max()
    assert err < 1e-3


def test_euler_passes_the_right_times():
    seen = []
    flow.sample_ode(lambda x, t: (seen.append(t.clone()), torch.zeros_like(x))[1], torch.zeros(2, 1), steps=4)
    assert torch.allclose(torch.stack(seen)[:, 0], torch.tensor([0.0, 0.25, 0.5, 0.75]))


def test_flow_matching_loss_is_zero_at_its_known_minimiser_and_positive_elsewhere():
    # all data at one point c: then x1 - x0 = (c - x_t) / (1 - t) exactly, so that field has zero loss
    torch.manual_seed(0)
    c = torch.tensor([1.0, -2.0, 0.5])
    x1 = c.expand(64, 3)
    x0, t = torch.randn(64, 3), torch.rand(64) * 0.99
    v_star = lambda x, tt: (c - x) / (1 - tt[:, None])
    assert flow.flow_matching_loss(v_star, x0, x1, t) < 1e-8
    assert flow.flow_matching_loss(lambda x, tt: v_star(x, tt) + 0.1, x0, x1, t) > 1e-3
    # per-sample weights: zero weight gives zero loss
    assert flow.flow_matching_loss(lambda x, tt: v_star(x, tt) + 0.1, x0, x1, t, weight=torch.zeros(64)) == 0


def test_classifier_free_guidance_combines_the_two_fields_as_stated():
    """v_w = v_u + w (v_c - v_u): w = 1 is the conditional field itself (one forward a step), w = 0 the
    unconditional one; on constant fields Euler integrates v_w exactly."""
    x0, c, u = torch.randn(4, 3), torch.randn(4, 3), torch.randn(4, 3)
    v_c, v_u = (lambda x, t: c), (lambda x, t: u)
    assert flow.guided_field(v_c, v_u, 1.0) is v_c
    t = torch.zeros(4)
    assert torch.equal(flow.guided_field(v_c, v_u, 0.0)(x0, t), u)
    for w in (0.5, 3.0):
        assert torch.allclose(flow.guided_field(v_c, v_u, w)(x0, t), u + w * (c - u))
        assert torch.allclose(flow.sample_ode(flow.guided_field(v_c, v_u, w), x0, steps=5), x0 + u + w * (c - u),
                              atol=1e-6)
