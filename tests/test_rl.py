"""rl.py and flow.py's SDE sampler: advantages, log-probs, ratios, clips, weightings, KL, and that each objective
actually climbs a reward on a tiny problem."""
import math

import pytest
import torch

import flow
import models
import rl


# ---- advantages and Eq. 10 ----------------------------------------------------------------------------------------

def test_group_advantages_standardise_each_group_and_are_zero_for_ties():
    r = torch.tensor([1.0, 2.0, 3.0, 5.0, 5.0, 5.0, 0.0, 10.0])
    g = torch.tensor([0, 0, 0, 1, 1, 1, 2, 2])
    A = rl.group_advantages(r, g)
    for k in (0, 2):
        a = A[g == k]
        assert abs(a.mean().item()) < 1e-6 and abs(a.std(unbiased=False).item() - 1) < 1e-4
    assert torch.equal(A[g == 1], torch.zeros(3))                      # all equal: zero, not NaN
    assert torch.isfinite(A).all()


def test_group_advantages_skip_invalid_rewards():
    r = torch.tensor([1.0, float("nan"), 3.0])
    A = rl.group_advantages(r, torch.zeros(3, dtype=torch.long))
    assert A[1] == 0 and torch.allclose(A[[0, 2]], torch.tensor([-1.0, 1.0]), atol=1e-5)


def test_reward_aggregation_on_a_hand_made_group():
    # one group of 4: r_task decides in [-6, 6], r_distill is tiny
    r_task = torch.tensor([6.0, -6.0, 6.0, -6.0])
    r_distill = torch.tensor([-0.001, -0.001, -0.003, -0.003])
    rewards, g = {"task": r_task, "distill": r_distill}, torch.zeros(4, dtype=torch.long)
    w = {"task": 1.0, "distill": 1.0}
    assert torch.allclose(rl.total_reward(rewards, w), r_task + r_distill)           # Eq. 10
    assert torch.allclose(rl.total_reward(rewards, {"task": 0.5, "distill": 2.0}), 0.5 * r_task + 2.0 * r_distill)
    no_judgment = {"task": r_task, "distill": torch.full((4,), float("nan"))}       # a weight of 0 leaves it out
    assert torch.equal(rl.total_reward(no_judgment, {"task": 1.0, "distill": 0.0}), r_task)
    with pytest.raises(ValueError, match="every reward weight is zero"):                # not an empty stack's error
        rl.total_reward(rewards, {"task": 0.0, "distill": 0.0})
    A_sum = rl.advantages(rewards, w, g, "sum", clip=None)
    # under plain sum the distillation reward barely moves the advantages ...
    assert torch.allclose(A_sum, torch.tensor([1.0, -1.0, 1.0, -1.0]), atol=1e-3)
    # ... under gdpo each reward counts in units of its own spread: the teacher-agreeing success ranks first
    A_gdpo = rl.advantages(rewards, w, g, "gdpo", clip=None)
    expect = torch.tensor([2.0, 0.0, 0.0, -2.0])                     # (+1+1), (-1+1), (+1-1), (-1-1)
    expect = (expect - expect.mean()) / expect.std(unbiased=False)
    assert torch.allclose(A_gdpo, expect, atol=2e-3)
    assert A_gdpo.argmax() == 0 and A_gdpo.argmin() == 3
    # clipping and a NaN reward
    assert rl.advantages({"task": torch.tensor([0.0, 0.0, 0.0, 100.0])}, {"task": 1.0}, g, "sum", clip=1.0).max() == 1.0
    A = rl.advantages({"task": torch.tensor([1.0, float("nan"), 0.0, 2.0])}, {"task": 1.0}, g, "gdpo")
    assert A[1] == 0 and torch.isfinite(A).all()
    with pytest.raises(ValueError):
        rl.advantages(rewards, w, g, "mean")


def test_per_step_rewards_give_per_step_advantages():
    """App. A.3's per-step r_distill: a reward of shape (N, S) makes advantages (N, S), each step normalised over its
    group as a per-rollout reward is; per-rollout rewards count alike at every step; a NaN zeroes its rollout."""
    g = torch.tensor([0, 0, 0, 0, 1, 1, 1, 1])
    r_task = torch.tensor([1.0, 2.0, 3.0, 4.0, 0.0, 0.0, 1.0, 1.0])
    r_step = torch.randn(8, 3, generator=torch.Generator().manual_seed(0))
    r_step[:, 2] = 0.0                                      # the last transition's credit is 0 for every rollout
    A = rl.group_advantages(r_step, g)
    assert A.shape == (8, 3) and torch.equal(A[:, 2], torch.zeros(8))
    for k in range(2):
        assert torch.equal(A[:, k], rl.group_advantages(r_step[:, k], g))
    w = {"task": 1.0, "distill": 1.0}
    A_sum = rl.advantages({"task": r_task, "distill": r_step}, w, g, "sum", clip=None)
    for k in range(3):
        assert torch.allclose(A_sum[:, k], rl.advantages({"task": r_task, "distill": r_step[:, k]}, w, g, "sum",
                                                         clip=None))
    A_gdpo = rl.advantages({"task": r_task, "distill": r_step}, w, g, "gdpo", clip=None)
    assert A_gdpo.shape == (8, 3)
    assert abs(A_gdpo.mean().item()) < 1e-6 and abs(A_gdpo.std(unbiased=False).item() - 1) < 1e-4   # over all N x S
    r_task[1] = float("nan")
    A = rl.advantages({"task": r_task, "distill": r_step}, w, g, "gdpo")
    assert torch.equal(A[1], torch.zeros(3)) and torch.isfinite(A).all()


def test_final_loss_is_eq12():
    assert rl.final_loss(torch.tensor(2.0), torch.tensor(3.0), 0.5).item() == 3.5
    assert rl.final_loss(torch.tensor(2.0), None, 0.5).item() == 2.0


# ---- the SDE sampler ------------------------------------------------------------------------------------------------

def test_sde_step_log_prob_is_the_gaussian_density():
    g = torch.Generator().manual_seed(0)
    x, v = torch.randn(3, 4, 5, generator=g), torch.randn(3, 4, 5, generator=g)
    t = torch.tensor([0.0, 0.3, 0.9])
    x_next, lp, mu, s = flow.sde_step(v, x, t, 0.1, 0.7, t_min=0.1, generator=g)
    direct = torch.distributions.Normal(mu, s.reshape(-1, 1, 1)).log_prob(x_next).flatten(1).mean(1)
    assert torch.allclose(lp, direct, atol=1e-5)
    # evaluating a given x_next gives the same number
    _, lp2, _, _ = flow.sde_step(v, x, t, 0.1, 0.7, t_min=0.1, x_next=x_next)
    assert torch.allclose(lp, lp2)


def _gaussian_velocity(m: float, sd: float):
    """Exact velocity of Eq. 2 for data N(m, sd^2) and noise N(0, 1): E[x_1 - x_0 | x_t]."""
    def v(x, t):
        t = t.reshape(-1, *([1] * (x.dim() - 1)))
        var = (1 - t) ** 2 + t ** 2 * sd ** 2
        d = x - t * m
        return m + t * sd ** 2 / var * d - (1 - t) / var * d
    return v


def test_sde_sampler_keeps_the_ode_marginals():
    v = _gaussian_velocity(2.0, 0.5)
    x0 = torch.randn(20000, 1, generator=torch.Generator().manual_seed(1))
    x_ode = flow.sample_ode(v, x0, 100)
    xs, ts, lp = flow.sample_sde(v, x0, 100, noise_level=0.7, generator=torch.Generator().manual_seed(2))
    x_sde = xs[-1]
    for x in (x_ode, x_sde):
        assert abs(x.mean().item() - 2.0) < 0.03 and abs(x.std().item() - 0.5) < 0.03
    assert lp.shape == (20000, 100) and not torch.equal(x_ode, x_sde)
    with pytest.raises(ValueError):
        flow.sample_sde(v, x0, 10, noise_level=0.0)


def test_sde_sampler_given_noises_samples_what_its_own_draws_sample():
    """sample_sde(noises=...) (a multi-process run's slice of the batch's draws) is the sampler with those standard
    normal draws: the same states and log-probs as drawing them from a generator in the same order."""
    v = _gaussian_velocity(1.0, 0.5)
    x0 = torch.randn(5, 3, generator=torch.Generator().manual_seed(0))
    xs, ts, lp = flow.sample_sde(v, x0, 4, noise_level=0.7, generator=torch.Generator().manual_seed(3))
    g = torch.Generator().manual_seed(3)
    noises = torch.stack([torch.randn(x0.shape, generator=g) for _ in range(4)])
    xs2, ts2, lp2 = flow.sample_sde(v, x0, 4, noise_level=0.7, noises=noises)
    assert torch.allclose(xs2, xs, atol=1e-6) and torch.allclose(lp2, lp, atol=1e-5) and torch.equal(ts2, ts)


# ---- ratios, clip, weighting, KL --------------------------------------------------------------------------------------

class Tiny(torch.nn.Module):
    """v(x, t | c) = lin(x) + bias: enough to have parameters, adapters and a condition dict."""

    def __init__(self, d: int = 6):
        super().__init__()
        self.lin = torch.nn.Linear(d, d)
        self.bias = torch.nn.Linear(1, d, bias=False)

    def forward(self, x, t, c):
        return self.lin(x) * 0.1 + self.bias(c["one"]) + 0 * t[:, None]


def _tiny_rollouts(model, n=8, steps=5, sde=True, seed=0):
    g = torch.Generator().manual_seed(seed)
    c = {"one": torch.ones(n, 1)}
    x0 = torch.randn(n, 6, generator=g)
    with torch.no_grad():
        if sde:
            xs, ts, lp = flow.sample_sde(lambda x, t: model(x, t, c), x0, steps, 0.7, g)
        else:
            xs, ts = flow.sample_ode(lambda x, t: model(x, t, c), x0, steps, return_trajectory=True)
            lp = None
    return rl.Rollouts(xs, ts, c, lp, 0.7)


def test_first_inner_step_ratio_is_one():
    torch.manual_seed(0)
    model = Tiny()
    models.add_lora(model, 2, 4.0)
    ro = _tiny_rollouts(model)
    A = torch.randn(8)
    cfg = rl.RLConfig()
    lp = rl._step_log_probs(model, ro)
    assert torch.allclose((lp - ro.log_probs).exp(), torch.ones_like(lp), atol=1e-6)
    for name in ("flow-grpo", "awm"):
        _, info = rl.OBJECTIVES[name](model, ro, A, cfg)
        assert abs(info["ratio_mean"] - 1) < 1e-6
    with pytest.raises(ValueError, match="unknown AWM ratio 'nope'"):
        rl.awm(model, ro, A, rl.RLConfig(ratio="nope"))


def test_per_step_advantages_weigh_each_transition_and_only_transition_objectives_take_them():
    """grpo and flow_grpo take A (N, S): a per-rollout A repeated at every step is the per-rollout loss, and an
    advantage on one step alone moves only that step's term; awm and nft score whole samples and refuse it."""
    torch.manual_seed(0)
    model = Tiny()
    models.add_lora(model, 2, 4.0)
    for name, p in model.named_parameters():
        if "lora_B" in name:
            p.data.normal_(0, 0.1)
    ro = _tiny_rollouts(model)
    A, S, cfg = torch.randn(8), ro.xs.shape[0] - 1, rl.RLConfig()
    for name in ("grpo", "flow-grpo"):
        one, _ = rl.OBJECTIVES[name](model, ro, A, cfg)
        per, _ = rl.OBJECTIVES[name](model, ro, A[:, None].expand(-1, S), cfg)
        assert torch.allclose(one, per, atol=1e-6), name
    lp = rl._step_log_probs(model, ro).detach()                     # (N, S)
    A_k = torch.zeros(8, S)
    A_k[:, 1] = A
    loss, _ = rl.grpo(model, ro, A_k, cfg)
    assert torch.allclose(loss, -(A * lp[:, 1]).mean(), atol=1e-6)      # only step 1's log-probs count
    with pytest.raises(ValueError, match="per-transition"):
        rl.nft(model, ro, A_k, cfg)
    # AWM takes them only on the sampler's grid (exp_first): the term at t = t_k gets A_k
    with pytest.raises(ValueError, match="per-transition"):
        rl.awm(model, ro, A_k, cfg)                                             # uniform re-noising times
    grid = rl.RLConfig(times="grid", timesteps=3)
    one, _ = rl.awm(model, _tiny_rollouts(model, seed=1), A, grid, torch.Generator().manual_seed(0))
    per, _ = rl.awm(model, _tiny_rollouts(model, seed=1), A[:, None].expand(-1, S), grid,
                    torch.Generator().manual_seed(0))
    assert torch.allclose(one, per, atol=1e-7)
    ro = _tiny_rollouts(model, seed=1)
    A_rand = torch.randn(8, S)
    loss, _ = rl.awm(model, ro, A_rand, grid, torch.Generator().manual_seed(0))
    _, t, _ = ro.draws["renoise"]
    k = torch.searchsorted(ro.ts[:-1], t).reshape(3, 8)                      # the grid step of each re-noised time
    assert torch.equal(ro.ts[:-1][k].reshape(-1), t)
    assert torch.allclose(loss, -(A_rand.T.gather(0, k)).mean(), atol=1e-6)   # ratio 1: loss = -mean A_k^i


def test_ppo_clip_as_stated():
    ratio = torch.tensor([0.5, 1.0, 1.5, 0.5, 1.5])
    A = torch.tensor([1.0, 1.0, 1.0, -1.0, -1.0])
    loss = rl._ppo(ratio, A, 0.2)
    # A > 0: the gain is capped at ratio 1.2, a drop below 0.8 is not; A < 0: the mirror image
    assert torch.allclose(loss, torch.tensor([-0.5, -1.0, -1.2, 0.8, 1.5]))
    # the gradient vanishes where the clip binds in the policy's favour
    r = ratio.clone().requires_grad_(True)
    rl._ppo(r, A, 0.2).sum().backward()
    assert torch.allclose(r.grad, torch.tensor([-1.0, -1.0, 0.0, 0.0, 1.0]))


def test_awm_weighting_on_hand_made_inputs():
    err, t = torch.tensor([4.0, 4.0, 0.25]), torch.tensor([0.0, 0.5, 0.5])
    assert torch.allclose(rl.awm_weight(err, t, "uniform"), err)
    assert torch.allclose(rl.awm_weight(err, t, "t"), torch.tensor([4.0, 2.0, 0.125]))
    assert torch.allclose(rl.awm_weight(err, t, "huber"), torch.tensor([2.0, 1.0, 0.25]), atol=1e-4)
    assert torch.allclose(rl.awm_weight(err, t, "ghuber", 0.5), 2 * rl.awm_weight(err, t, "huber"), atol=1e-4)
    assert torch.allclose(rl.awm_weight(err, t, "ghuber", 1.0), rl.awm_weight(err, t, "t"), atol=1e-5)
    # the Huber forms grow slower than the error: 16x the error is 4x the weight
    assert math.isclose(rl.awm_weight(torch.tensor([64.0]), torch.tensor([0.0]), "huber").item(), 8.0, rel_tol=1e-4)
    with pytest.raises(ValueError):
        rl.awm_weight(err, t, "cubic")


def test_awm_ratio_per_time_or_per_sample_as_stated():
    """At a later inner epoch (the LoRA moved since theta_old was recorded) AWM's ratio is
    exp(log pi - log pi_old) per (sample, time) for exp_first and exp(mean_t log pi - mean_t log pi_old) per sample
    for sum_first, log pi = -rho(||v - u||^2, t) at the held re-noising draws; with no clip binding the loss is
    -mean(A r). The two differ once the log-ratios differ across times."""
    A, n_t, losses = torch.randn(8), 3, {}
    for kind in ("exp_first", "sum_first"):
        torch.manual_seed(0)
        model = Tiny()
        models.add_lora(model, 2, 4.0)
        cfg = rl.RLConfig(timesteps=n_t, ratio=kind, clip_range=100.0)
        ro = _tiny_rollouts(model, seed=1)
        rl.awm(model, ro, A, cfg, torch.Generator().manual_seed(0))                 # records theta_old's log pi
        with torch.no_grad():
            for p in models.lora_parameters(model):
                p.add_(0.2 * torch.randn_like(p))
        loss, _ = rl.awm(model, ro, A, cfg)
        x_t, t, u = ro.draws["renoise"]
        c = {k: v.repeat(n_t, *([1] * (v.dim() - 1))) for k, v in ro.c.items()}
        with torch.no_grad():
            logp = -rl.awm_weight(rl._sq(model(x_t, t, c) - u), t, cfg.weighting, cfg.ghuber_power).reshape(n_t, 8)
        d = logp - ro.draws["awm_old"]                                                     # (n_t, N) log-ratios
        assert d.abs().min() > 1e-4 and (d - d.mean(0)).abs().max() > 1e-3             # the LoRA moved, unevenly
        r = d.exp() if kind == "exp_first" else d.mean(0).exp()[None]
        assert torch.allclose(loss, -(A[None] * r).mean(), atol=1e-6), kind
        losses[kind] = loss.item()
    assert abs(losses["exp_first"] - losses["sum_first"]) > 1e-5


def test_nft_optimality_scales_with_the_advantage_up_to_a_max():
    """DiffusionNFT's r = 1/2 + 1/2 clip(A / A_max, -1, 1), A_max = cfg.adv_max. At the first inner step
    v+ = v- = v_old, so the loss's gradient is (2r - 1) 2 beta (v - u) dv/dtheta: proportional to clip(A / A_max),
    full at A = A_max, no more beyond it, reversed for -A_max."""
    torch.manual_seed(0)
    model = Tiny()
    models.add_lora(model, 2, 4.0)
    params = models.lora_parameters(model)

    def grad(a, a_max):
        ro = _tiny_rollouts(model, sde=False)
        loss, _ = rl.nft(model, ro, torch.full((8,), float(a)), rl.RLConfig(adv_max=a_max),
                         torch.Generator().manual_seed(0))
        return torch.cat([g.flatten() for g in torch.autograd.grad(loss, params)])

    full = grad(5, 5)
    assert full.abs().max() > 1e-4
    for a, a_max, scale in ((2.5, 5, 0.5), (10, 5, 1), (-5, 5, -1), (2, 2, 1), (1, 2, 0.5), (0, 2, 0)):
        assert torch.allclose(grad(a, a_max), scale * full, atol=1e-7), (a, a_max)


def test_renoising_times_stratified_uniform_or_on_the_samplers_grid():
    """_renoise: n_t strata per sample; "uniform" puts stratum j's time in [0.98 j/n_t, 0.98 (j+1)/n_t), "grid" on
    the sampler's step times that fall in stratum j of the S steps; the path and target are Eq. 2's either way."""
    ro = _tiny_rollouts(Tiny(), n=400, steps=10, sde=False)
    grid = ro.ts[:-1]
    for times in ("uniform", "grid"):
        ro.draws.clear()
        x_t, t, u = rl._renoise(ro, 4, torch.Generator().manual_seed(0), times)
        t = t.reshape(4, 400)
        if times == "uniform":
            for j in range(4):
                assert (t[j] >= 0.98 * j / 4).all() and (t[j] < 0.98 * (j + 1) / 4).all()
        else:
            hits = (t[..., None] == grid).sum(-1)
            assert (hits == 1).all()                                       # every time is one of the grid's
            k = (t * 10).round().long()
            assert (k[0] <= 2).all() and ((k[1] >= 2) & (k[1] <= 4)).all() and (k[3] >= 7).all()
            assert set(k.flatten().tolist()) == set(range(10))             # and every step time is drawn
        x1 = ro.x1.repeat(4, 1)
        eps = x1 - u
        assert torch.allclose(x_t, (1 - t.reshape(-1, 1)) * eps + t.reshape(-1, 1) * x1, atol=1e-6)
    with pytest.raises(ValueError):
        ro.draws.clear()
        rl._renoise(ro, 4, None, "logit")


def test_gaussian_kl_closed_form():
    mu = torch.randn(4, 3)
    s = torch.tensor([0.1, 0.2, 0.3, 0.4])
    assert torch.equal(rl.gaussian_kl(mu, mu, s), torch.zeros(4))
    mu2 = mu + 0.05
    direct = torch.distributions.kl_divergence(torch.distributions.Normal(mu, s[:, None]),
                                               torch.distributions.Normal(mu2, s[:, None])).mean(1)
    assert torch.allclose(rl.gaussian_kl(mu, mu2, s), direct, atol=1e-6)


@pytest.mark.parametrize("name", ["flow-grpo", "awm"])
def test_kl_to_the_reference_is_zero_at_init_grows_after_and_is_added_to_the_loss(name):
    """Flow-GRPO's closed-form KL and AWM's velocity-space KL to the base: zero while the LoRA is at init, positive
    once it moved, and a penalty -- with zero advantages (no policy-gradient term) the loss is + kl_beta KL."""
    torch.manual_seed(0)
    model = Tiny()
    models.add_lora(model, 2, 4.0)
    ro = _tiny_rollouts(model)
    cfg = rl.RLConfig(kl_beta=0.5)
    _, info = rl.OBJECTIVES[name](model, ro, torch.zeros(8), cfg)
    assert abs(info["kl"]) < 1e-10
    with torch.no_grad():
        for p in models.lora_parameters(model):
            p.add_(0.3)
    ro.draws.clear()
    loss, info = rl.OBJECTIVES[name](model, ro, torch.zeros(8), cfg)
    assert info["kl"] > 1e-4 and loss.item() == pytest.approx(0.5 * info["kl"], rel=1e-5)


def test_objectives_need_the_right_rollouts():
    model = Tiny()
    ro = _tiny_rollouts(model, sde=False)
    for name in rl.NEEDS_SDE:
        with pytest.raises(ValueError):
            rl.OBJECTIVES[name](model, ro, torch.zeros(8), rl.RLConfig())


@pytest.mark.parametrize("name", list(rl.OBJECTIVES))
def test_each_objective_climbs_a_reward(name):
    """Reward = mean of the final sample. A few updates of each objective, from groups of rollouts, must raise the
    mean reward of fresh rollouts -- and a zero advantage must leave the LoRA untouched."""
    torch.manual_seed(0)
    model = Tiny()
    models.add_lora(model, 2, 4.0)
    params = models.lora_parameters(model)
    opt = torch.optim.Adam(params, lr=0.05)
    cfg = rl.RLConfig(timesteps=2)
    sde = name in rl.NEEDS_SDE

    def mean_reward(seed):
        return _tiny_rollouts(model, 256, sde=sde, seed=seed).x1.mean().item()

    before = mean_reward(100)
    groups = torch.arange(4).repeat_interleave(8)
    for step in range(15):
        ro = _tiny_rollouts(model, 32, sde=sde, seed=step)
        A = rl.advantages({"r": ro.x1.mean(1)}, {"r": 1.0}, groups)
        loss, _ = rl.OBJECTIVES[name](model, ro, A, cfg, torch.Generator().manual_seed(step))
        opt.zero_grad()
        loss.backward()
        opt.step()
    assert mean_reward(100) > before + 0.3
    # zero advantages: no gradient on the LoRA (the objective is a pure policy gradient)
    ro = _tiny_rollouts(model, 32, sde=sde, seed=99)
    loss, _ = rl.OBJECTIVES[name](model, ro, torch.zeros(32), cfg)
    opt.zero_grad()
    loss.backward()
    assert all(p.grad is None or p.grad.abs().max() < 1e-7 for p in params)
