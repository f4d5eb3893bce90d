"""distill.py: losses vanish exactly when Executor and Demonstrator agree, Eq. 9 against a hand computation,
detached states, DMD's gradient, and a numerical check of Proposition 1."""
import copy
import math

import numpy as np
import pytest
import torch
import torch.nn as nn

import distill
import flow
import models
import world


class Linear(nn.Module):
    """v(x, t | c) = a_c x, with a_c a number carried in the condition: the Demonstrator and Executor are the same
    module (no adapters), differing only in their condition, so every quantity has a closed form."""

    def forward(self, x, t, c):
        return c["a"] * x


def test_eq9_matches_a_hand_computed_integral():
    a_E, a_D, S = 0.5, -0.25, 4
    x0 = torch.tensor([[1.0, 2.0], [-1.0, 0.5]])
    m = Linear()
    traj = distill.rollout(m, x0, {"a": a_E}, S)
    r = distill.distill_reward(m, traj, {"a": a_E}, {"a": a_D})
    # Euler on dx/dt = a_E x: x_k = (1 + a_E / S)^k x0; l_k = mean((a_E - a_D)^2 x_k^2); r = -sum_k (1/S) l_k
    want = -sum((1 / S) * ((a_E - a_D) ** 2) * ((1 + a_E / S) ** k * x0).pow(2).mean(1) for k in range(S))
    assert torch.allclose(r, want, atol=1e-6)
    per_step = distill.distill_reward(m, traj, {"a": a_E}, {"a": a_D}, per_step=True)
    assert per_step.shape == (2, S) and torch.allclose(per_step.sum(1), r)
    assert torch.all(distill.distill_reward(m, traj, {"a": a_E}, {"a": a_E}) == 0)
    # App. A.3 as credit: transition k (x_k -> x_{k+1}) gets the terms after it, sum_{j > k} r_j; the last gets 0
    G = distill.distill_reward_to_go(per_step)
    want_G = torch.stack([per_step[:, k + 1:].sum(1) for k in range(S)], 1)
    assert G.shape == (2, S) and torch.allclose(G, want_G) and torch.equal(G[:, -1], torch.zeros(2))
    assert torch.equal(distill.distill_reward_to_go(torch.tensor([[-1.0, -2.0, -3.0, -4.0]])),
                       torch.tensor([[-9.0, -7.0, -4.0, 0.0]]))


@pytest.fixture(scope="module")
def lora_model():
    torch.manual_seed(0)
    m = models.make_model("toy", width=16, emb_dim=32, text_dim=32)
    nn.init.normal_(m.out.weight, std=0.05)  # a fresh model ignores its input; fake a trained one
    models.add_lora(m, rank=4, alpha=8)
    pairs = world.make_pairs(4, seed=3, error_rate=0.0)
    frame0 = np.stack([p.frame0 for p in pairs])
    c_E = m.condition(frame0, [p.task.text for p in pairs])
    c_D = m.condition(frame0, [p.d_oracle for p in pairs])
    x0 = torch.randn(4, *m.latent_shape(), generator=torch.Generator().manual_seed(0))
    return m, c_E, c_D, x0


def _lora_B(m):
    return [p for n, p in m.named_parameters() if n.endswith("lora_B")]


def _perturb(m, scale):
    for p in _lora_B(m):
        p.data.normal_(0, scale) if scale else p.data.zero_()


@pytest.mark.parametrize("which", ["off", "on", "anchor"])
def test_losses_are_zero_iff_executor_equals_demonstrator(lora_model, which):
    m, c_E, c_D, x0 = lora_model
    _perturb(m, 0)
    fn = {"off": distill.off_policy_loss, "on": distill.on_policy_loss, "anchor": distill.anchor_loss}[which]
    traj = lambda c_cond, demo: distill.rollout(m, x0, c_cond, 3, demonstrator=demo)
    # same condition on both sides and B = 0: the Executor *is* the Demonstrator
    assert fn(m, traj(c_D, which == "off"), c_D, c_D).item() == 0.0
    # different conditions (T vs D): positive
    assert fn(m, traj(c_D if which == "off" else c_E, which == "off"), c_E, c_D).item() > 0
    # same condition but trained adapters: positive
    _perturb(m, 0.05)
    assert fn(m, traj(c_D, which == "off"), c_D, c_D).item() > 0
    _perturb(m, 0)


def test_state_window_draws_only_its_grid_times_and_all_t_is_the_default():
    S, B = 10, 4000
    xs = torch.arange(S + 1, dtype=torch.float32)[:, None, None].expand(S + 1, B, 3)   # state k holds the number k
    ts = flow.time_grid(S)
    g = lambda: torch.Generator().manual_seed(0)
    x, t = distill._pick_states(xs, ts, g(), window=(0.3, 0.7))
    assert set(x[:, 0].long().tolist()) == {3, 4, 5, 6} and torch.equal(t, ts[x[:, 0].long()])
    # no window: every grid step but the last state, and the very draws of the window [0, 1)
    x_all, _ = distill._pick_states(xs, ts, g())
    assert set(x_all[:, 0].long().tolist()) == set(range(S))
    assert torch.equal(x_all, distill._pick_states(xs, ts, g(), window=(0.0, 1.0))[0])
    # a window is an index map on the default draws: the same as U{lo .. hi-1} drawn directly
    assert torch.equal(x[:, 0].long(), torch.randint(3, 7, (B,), generator=g()))
    with pytest.raises(ValueError, match="no grid time"):
        distill._pick_states(xs, ts, g(), window=(0.31, 0.39))


def test_motion_weight_weighs_the_pixels_the_demonstrator_moves():
    """squared_error: weight w on the pixels whose Demonstrator clean estimate x_t + (1 - t) v_D differs from the
    first frame, 1 elsewhere; w = 1 is Eq. 4's plain mean."""
    B, T, C, H, W = 2, 2, 3, 4, 4
    frame0 = torch.zeros(B, C, H, W)
    x_t, t = torch.zeros(B, T, C, H, W), torch.tensor([0.0, 0.5])
    v_D = torch.zeros(B, T, C, H, W)
    v_D[0, 1, :, 2, 3] = 1.0           # sample 0: the Demonstrator moves one pixel of frame 2 (x̂_1 = 1 there)
    v_E = v_D + 0.1                    # the Executor is off by 0.1 everywhere ...
    v_E[1, 0, 0, 0, 0] = 1.1           # ... and sample 1 by 1.1 at one value; its Demonstrator moves nothing
    c_D = {"frame0": frame0}
    plain = distill.squared_error(v_E, v_D, x_t, t, c_D)
    n = T * C * H * W
    assert torch.allclose(plain, torch.tensor([0.01, (0.01 * (n - 1) + 1.21) / n]))
    w = distill.squared_error(v_E, v_D, x_t, t, c_D, motion_weight=10.0)
    assert torch.allclose(w, torch.tensor([0.01 * (n - 3 + 3 * 10) / n, plain[1].item()]))


def test_eq9_and_the_anchor_read_the_demonstrators_velocities_computed_once(lora_model):
    """train.py computes the Demonstrator along the Executor's trajectory once (teacher_velocities): Eq. 9 uses every
    state's, Eq. 11 its drawn state's. Both must equal what they compute on their own, draws included."""
    m, c_E, c_D, x0 = lora_model
    _perturb(m, 0.05)
    traj = distill.rollout(m, x0, c_E, 4)
    v_D = distill.teacher_velocities(m, traj, c_D)
    assert v_D.shape == (4, *x0.shape)

    def g():
        return torch.Generator().manual_seed(1)

    for kw in ({}, {"window": (0.25, 0.75), "motion_weight": 10.0}):
        own = distill.anchor_loss(m, traj, c_E, c_D, g(), **kw)
        read = distill.anchor_loss(m, traj, c_E, c_D, g(), teacher_v=v_D, **kw)
        assert own > 0 and torch.allclose(read, own, rtol=1e-5, atol=0)
        assert not torch.allclose(distill.anchor_loss(m, traj, c_E, c_D, g(), teacher_v=0 * v_D, **kw), own)
    assert torch.allclose(distill.distill_reward(m, traj, c_E, c_D, teacher_v=v_D),
                          distill.distill_reward(m, traj, c_E, c_D), rtol=1e-5, atol=0)
    _perturb(m, 0)


def test_eq3_reads_the_velocities_the_demonstrators_sampler_took(lora_model):
    """rollout(..., velocities=True) returns the trajectory it returns without them and, at every grid state, the
    velocity its sampler took there: on the Demonstrator's own trajectory under c_D, Eq. 3's targets. Eq. 3 with them
    (teacher_v) equals Eq. 3 computing its target again at the drawn state, draws and gradients included."""
    m, c_E, c_D, x0 = lora_model
    _perturb(m, 0.05)
    traj, v_D = distill.rollout(m, x0, c_D, 4, demonstrator=True, velocities=True)
    xs, ts = distill.rollout(m, x0, c_D, 4, demonstrator=True)
    assert torch.equal(traj[0], xs) and torch.equal(traj[1], ts) and v_D.shape == (4, *x0.shape)
    assert torch.allclose(v_D, distill.teacher_velocities(m, traj, c_D), rtol=1e-5, atol=1e-7)

    def loss_and_grads(**kw):
        for p in _lora_B(m):
            p.grad = None
        loss = distill.off_policy_loss(m, traj, c_E, c_D, torch.Generator().manual_seed(1), **kw)
        loss.backward()
        return loss.detach(), [p.grad.clone() for p in _lora_B(m)]

    for kw in ({}, {"window": (0.25, 0.75), "motion_weight": 10.0}):
        own, own_g = loss_and_grads(**kw)
        read, read_g = loss_and_grads(teacher_v=v_D, **kw)
        assert own > 0 and torch.allclose(read, own, rtol=1e-5, atol=0)
        assert all(torch.allclose(a, b, rtol=1e-4, atol=1e-9) for a, b in zip(read_g, own_g))
        assert not torch.allclose(loss_and_grads(teacher_v=v_D.flip(0), **kw)[0], own)   # another state's target
    _perturb(m, 0)


def test_the_demonstrators_rollout_is_a_given_teachers(lora_model):
    """rollout(..., demonstrator=True, teacher=net) is the separate network's trajectory (Alg. 2's phi, the frozen
    base beside an every-weight Executor), velocities included, with its own adapters on -- as teacher_velocity
    reads it; without a teacher, `model` with adapters off. A teacher without demonstrator=True is refused."""
    m, c_E, c_D, x0 = lora_model
    _perturb(m, 0)
    teacher = copy.deepcopy(m)
    _perturb(teacher, 0.05)      # phi: adapters of its own, on
    traj, v_D = distill.rollout(m, x0, c_D, 4, demonstrator=True, velocities=True, teacher=teacher)
    xs, ts = flow.sample_ode(lambda x, t: teacher(x, t, c_D), x0, 4, return_trajectory=True)
    assert torch.allclose(traj[0], xs, rtol=1e-5, atol=1e-6) and torch.equal(traj[1], ts)
    assert torch.allclose(v_D, distill.teacher_velocities(m, traj, c_D, teacher), rtol=1e-5, atol=1e-7)
    assert not torch.allclose(traj[0], distill.rollout(m, x0, c_D, 4, demonstrator=True)[0])   # not m's, adapters off
    with pytest.raises(ValueError, match="demonstrator=True"):
        distill.rollout(m, x0, c_E, 4, teacher=teacher)


def test_on_policy_states_are_detached(lora_model):
    m, c_E, c_D, x0 = lora_model
    _perturb(m, 0.05)
    x0 = x0.clone().requires_grad_(True)
    xs, ts = flow.sample_ode(lambda x, t: m(x, t, c_E), x0, 3, return_trajectory=True)  # with grad, on purpose
    loss = distill.anchor_loss(m, (xs, ts), c_E, c_D)
    loss.backward()
    assert x0.grad is None  # nothing flows back into the sampler (Eq. 11's sg)
    assert all(p.grad is not None for p in _lora_B(m))
    assert not distill.rollout(m, x0.detach(), c_E, 3)[0].requires_grad
    m.zero_grad(set_to_none=True)
    _perturb(m, 0)


def test_dmd_gradient_is_zero_when_fake_equals_real_and_points_from_fake_to_real(lora_model):
    m, c_E, c_D, x0 = lora_model
    _perturb(m, 0)
    fake = distill.make_fake_score(m)
    x = x0.clone().requires_grad_(True)
    distill.dmd_generator_loss(m, fake, x, c_D, c_D, torch.Generator().manual_seed(1)).backward()
    assert torch.all(x.grad == 0)  # fake score == real score: nothing to match
    x.grad = None
    distill.dmd_generator_loss(m, fake, x, c_E, c_D, torch.Generator().manual_seed(1)).backward()
    g = torch.Generator().manual_seed(1)                      # dmd_generator_loss's draws: t, then the noise
    t = torch.rand(x.shape[0], generator=g).clamp(0.02, 0.98)
    x_t = flow.interpolate(torch.randn(x.shape, generator=g), x.detach(), t)
    with torch.no_grad(), models.adapters_disabled(m):
        to_real = distill._denoise(m, x_t, t, c_D) - distill._denoise(fake, x_t, t, c_E)   # mu_real - mu_fake
    cos = torch.nn.functional.cosine_similarity(-x.grad.flatten(1), to_real.flatten(1), dim=1)
    assert to_real.abs().sum() > 0 and torch.allclose(cos, torch.ones_like(cos), atol=1e-5)   # descent: fake -> real
    loss = distill.dmd_fake_score_loss(fake, x.detach(), c_E)
    loss.backward()
    assert loss.item() > 0 and all(p.grad is not None for p in models.lora_parameters(fake))


class PointMass(nn.Module):
    """The exact velocity of Eq. 2 for data that is one point x_star: v(x_t, t) = (x_star - x_t) / (1 - t), so its
    clean estimate mu(x_t, t) = x_t + (1 - t) v is x_star at every state."""

    def __init__(self, x_star):
        super().__init__()
        self.register_buffer("x_star", x_star)

    def forward(self, x, t, c):
        return (self.x_star - x) / flow._bcast(1 - t, x)


def test_eq18_is_zero_for_the_exact_denoiser_and_positive_for_a_wrong_one():
    """Eq. 18, || mu_fake(x_t, t) - x ||^2 with x_t ~ q_t(. | x): on samples x = x_star the point mass's exact
    denoiser scores 0; the identity denoiser mu(x_t) = x_t (v = 0) scores the noise it leaves in."""
    x_star = torch.randn(3, 2, 4, generator=torch.Generator().manual_seed(0))
    exact = distill.dmd_fake_score_loss(PointMass(x_star), x_star, {}, torch.Generator().manual_seed(1))
    still = distill.dmd_fake_score_loss(lambda x, t, c: torch.zeros_like(x), x_star, {},
                                        torch.Generator().manual_seed(1))
    assert exact.item() < 1e-10 and still.item() > 0.01


def test_fake_score_starts_as_the_base_with_only_its_own_lora_trainable(lora_model):
    """make_fake_score copies the base, not the Executor: the Executor's adapters are folded away (B = 0)."""
    m, c_E, c_D, x0 = lora_model
    _perturb(m, 0.05)
    fake = distill.make_fake_score(m)
    t = torch.full((x0.shape[0],), 0.3)
    with torch.no_grad():
        with models.adapters_disabled(m):
            base = m(x0, t, c_E)
        assert not torch.allclose(m(x0, t, c_E), base)                    # the Executor differs from the base ...
        torch.testing.assert_close(fake(x0, t, c_E), base)               # ... and the fake score starts as the base
    assert {n for n, p in fake.named_parameters() if p.requires_grad} == {n for n, _ in fake.named_parameters()
                                                                        if "lora_" in n}
    _perturb(m, 0)
    plain = models.make_model("toy", width=16, emb_dim=32, text_dim=32)      # a base without adapters gets its own
    nn.init.normal_(plain.out.weight, std=0.05)
    fake = distill.make_fake_score(plain, rank=2)
    trainable = [p for p in fake.parameters() if p.requires_grad]
    assert trainable and sum(p.numel() for p in trainable) == sum(p.numel() for p in models.lora_parameters(fake))
    assert not models.lora_parameters(plain)                                  # the base itself is left as it was
    with torch.no_grad():
        torch.testing.assert_close(fake(x0, t, c_E), plain(x0, t, c_E))


def test_alg2s_teacher_takes_the_demonstrators_place(lora_model):
    """teacher_velocity: the base with adapters off, or Alg. 2's separately trained `teacher` with its adapters on."""
    m, c_E, c_D, x0 = lora_model
    _perturb(m, 0)
    teacher = copy.deepcopy(m)
    _perturb(teacher, 0.05)
    t = torch.full((x0.shape[0],), 0.3)
    v = distill.teacher_velocity(m, x0, t, c_D, teacher)
    with torch.no_grad():
        torch.testing.assert_close(v, teacher(x0, t, c_D))
        assert not torch.allclose(v, distill.teacher_velocity(m, x0, t, c_D))
    assert not v.requires_grad


def test_dmd_generator_is_the_clean_estimate_at_a_detached_state_of_the_executors_trajectory(lora_model):
    m, c_E, c_D, x0 = lora_model
    _perturb(m, 0.05)
    traj = distill.rollout(m, x0, c_E, 4)
    x = distill.dmd_generator(m, traj, c_E, torch.Generator().manual_seed(2))
    k = torch.randint(0, 4, (4,), generator=torch.Generator().manual_seed(2))  # the same draw
    xs, ts = traj
    x_k, t_k = xs[k, torch.arange(4)], ts[k]
    with torch.no_grad():
        expect = x_k + (1 - t_k).reshape(-1, 1, 1, 1, 1) * m(x_k, t_k, c_E)
    torch.testing.assert_close(x.detach(), expect)
    assert not traj[0].requires_grad          # the trajectory is data; the gradient is this one call's
    x.pow(2).mean().backward()
    assert all(p.grad is not None for p in _lora_B(m))
    m.zero_grad(set_to_none=True)
    _perturb(m, 0)


def test_proposition_1_bound_on_linear_fields():
    """Teacher v'(x) = A x (L = ||A||_2), student v(x) = A x + delta. With shared x_0 both terminal laws are
    Gaussians with equal covariance, so W2 = ||Delta_1|| exactly; the bound says W2 <= e^L eps, with
    eps^2 = E int ||v - v'||^2 dt on the student's own trajectory = ||delta||^2 (squared norm = sum, as in Eq. 8)."""
    torch.manual_seed(0)
    d, n, S = 3, 256, 2000
    for trial in range(5):
        A = torch.randn(d, d) * 0.7
        delta = torch.randn(d) * 0.3
        L = torch.linalg.matrix_norm(A, ord=2).item()
        x0 = torch.randn(n, d)
        student = flow.sample_ode(lambda x, t: x @ A.T + delta, x0, S)
        teacher = flow.sample_ode(lambda x, t: x @ A.T, x0, S)
        gap = (student - teacher).norm(dim=1)  # the same for every sample: Delta_1 = int e^{A(1-s)} delta ds
        w2 = gap.pow(2).mean().sqrt().item()
        eps = delta.norm().item()
        assert gap.std() < 1e-3
        assert w2 <= math.exp(L) * eps + 1e-4, (w2, math.exp(L) * eps)
        exact = (torch.linalg.matrix_exp(A) - torch.eye(d)) @ torch.linalg.solve(A, delta)  # int_0^1 e^{As} ds delta
        assert abs(w2 - exact.norm().item()) < 5e-3 * (1 + exact.norm().item())
