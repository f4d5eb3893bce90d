"""Reinforcement learning from the judges: group-relative advantages and four policy-gradient objectives for flow
models (Sec. 3 Eqs. 10 and 12, App. A.9, Alg. 1 lines 5-11).

Alg. 1 in this repository's words: for each (first frame I, task T, description D) the Executor draws a group of
G rollouts tau_1..tau_G ~ p_theta(. | I, T); the judges (reward.py) score each; Eq. 9 (distill.distill_reward)
scores its agreement with the Demonstrator; Eq. 10 combines them; group-relative advantages (App. A.9) say which
rollouts beat their siblings; one of the objectives below turns advantages into a loss L_RL; Eq. 12 adds the
Demonstrator anchor (distill.anchor_loss). train.py's `rl` stage is that loop.

The four objectives are sibling functions with one signature,

    loss, info = objective(model, rollouts, advantages, cfg, generator)

on the Executor (model with adapters on, condition rollouts.c = c_E):
  grpo       App. A.9 "GRPO" [52]: -mean_i A_i log p_theta(tau_i), log p of the SDE rollout's transitions.
  flow_grpo  App. A.9 "FlowGRPO" [40]: per-step ratios, PPO clip, closed-form KL to the reference policy.
  awm        App. A.9 "Advantage Weighted Matching" [67]: the flow-matching loss on re-noised final samples as the
             log-likelihood surrogate; the paper's main trainer (Tab. 3: exp_first, ghuber, gdpo).
  nft        DiffusionNFT [71] (cited in Sec. 3 for L_RL): positive and negative implicit policies around the old
             velocity, trained with the forward process.

Reductions: every squared norm and Gaussian log-density is a *mean* over latent dimensions (flow.sde_step says
why); losses are means over rollouts (and timesteps).
"""
from __future__ import annotations

from dataclasses import dataclass, field

import torch

import flow
import models

# ----------------------------------------------------------------------------------------------------------------
# rewards and advantages (Eq. 10, App. A.9)
# ----------------------------------------------------------------------------------------------------------------


def total_reward(rewards: dict, weights: dict) -> torch.Tensor:
    """Eq. 10: R(tau) = lambda_task r_task(tau; I, T) + lambda_distill r_distill(tau), plus, as in Sec. 4.1
    "Rewards", lambda_cons r_cons(tau) for the consistency judge. rewards: {name: (N,)}, weights: {name: lambda};
    a reward whose weight is 0 is left out (so an unneeded NaN does not spread). Returns (N,)."""
    terms = [weights[k] * r for k, r in rewards.items() if weights.get(k, 0) != 0]
    if not terms:
        raise ValueError("total_reward: every reward weight is zero")
    return torch.stack(terms).sum(0)


def group_advantages(r: torch.Tensor, groups: torch.Tensor, eps: float = 1e-6) -> torch.Tensor:
    """App. A.9: A_i = (r_i - mu_r) / (sigma_r + eps), mu_r and sigma_r (population std, 1/G) over the G rollouts of
    the same (image, task). r: (N,), groups: (N,) integer group ids. A rollout whose reward is NaN (no judgment
    possible, Tab. 4) is skipped: it gets A = 0 and does not enter mu or sigma. A group whose rewards are all equal
    gets A = 0 (not NaN): it carries no preference. A per-step reward r (N, S) (App. A.3: one per rollout and
    transition) is normalised step by step, column k over the group's G values of step k: A (N, S)."""
    if r.dim() == 2:
        return torch.stack([group_advantages(r[:, k], groups, eps) for k in range(r.shape[1])], 1)
    A = torch.zeros_like(r)
    ok = torch.isfinite(r)
    for g in groups.unique():
        m = (groups == g) & ok
        if m.sum() == 0:
            continue
        x = r[m]
        A[m] = (x - x.mean()) / (x.std(unbiased=False) + eps)
    return A


def advantages(rewards: dict, weights: dict, groups: torch.Tensor, mode: str = "gdpo", clip: float | None = 5.0,
               eps: float = 1e-6) -> torch.Tensor:
    """Group-relative advantages of the Eq. 10 reward, aggregated one of two ways (Tab. 3 "Advantage aggregation"):

      sum   A = groupnorm(sum_k lambda_k r_k): normalise the total reward of Eq. 10 within each group.
      gdpo  A = batchnorm(sum_k lambda_k groupnorm(r_k)): normalise each reward within its group first, then sum,
            then standardise the sum over the batch (GDPO's decoupled normalisation). r_task lives in [-6, 6] and
            r_distill in ~[-1e-2, 0]: under `sum` the larger-scale reward decides the ranking unless lambda undoes
            the scale by hand; under `gdpo` each reward contributes in units of its own within-group spread.

    A rollout with any non-finite reward gets A = 0. Advantages are then clipped to [-clip, clip] (AWM and
    Flow-GRPO clip at 5). Returns (N,). A per-step reward (N, S) (App. A.3; train.py --distill_reward per_step)
    makes the advantages per step, (N, S): the per-rollout rewards count alike at every step, and gdpo's batch
    standardisation runs over all N x S; the per-transition objectives take them (grpo, flow_grpo, and awm on the
    sampler's grid)."""
    used = {k: r for k, r in rewards.items() if weights.get(k, 0) != 0}
    S = max((r.shape[1] for r in used.values() if r.dim() == 2), default=0)
    if S:
        used = {k: r if r.dim() == 2 else r[:, None].expand(-1, S) for k, r in used.items()}
    bad = ~torch.stack([torch.isfinite(r) for r in used.values()]).all(0)
    if mode == "sum":
        A = group_advantages(total_reward(used, weights).masked_fill(bad, float("nan")), groups, eps)
    elif mode == "gdpo":
        A = sum(weights[k] * group_advantages(r.masked_fill(bad, float("nan")), groups, eps) for k, r in used.items())
        good = ~bad
        if good.sum() > 1:
            a = A[good]
            A = torch.where(good, (A - a.mean()) / (a.std(unbiased=False) + eps), torch.zeros_like(A))
    else:
        raise ValueError(f"unknown advantage aggregation {mode!r}; choose sum or gdpo")
    A = A.masked_fill(bad, 0.0)
    return A.clamp(-clip, clip) if clip else A


def final_loss(l_rl: torch.Tensor, l_anchor: torch.Tensor | None, beta_d: float) -> torch.Tensor:
    """Eq. 12: L_final = L_RL + beta_d L_anchor (beta_d = 0 or no anchor: RL alone)."""
    return l_rl if (l_anchor is None or beta_d == 0) else l_rl + beta_d * l_anchor


# ----------------------------------------------------------------------------------------------------------------
# what the objectives consume
# ----------------------------------------------------------------------------------------------------------------

@dataclass
class Rollouts:
    """A batch of Executor rollouts: xs (S+1, N, ...) states, ts (S+1,) times, c the Executor's condition c_E for
    all N, log_probs (N, S) the SDE transitions' log-probs under the sampling policy (None for ODE rollouts),
    noise_level of that SDE. `draws` keeps what an objective must hold fixed across inner epochs (its re-noising
    times and noise, and the old policy's values at them) -- filled on first use."""
    xs: torch.Tensor
    ts: torch.Tensor
    c: dict
    log_probs: torch.Tensor | None = None
    noise_level: float = 0.7
    draws: dict = field(default_factory=dict)
    shard: tuple | None = None
    """(offset, total): these N rollouts are rows offset..offset+N-1 of a batch of `total` split across processes;
    random draws are made for the whole batch and sliced, so every process draws what one process would"""

    @property
    def x1(self) -> torch.Tensor:
        return self.xs[-1]


@dataclass
class RLConfig:
    clip_range: float = 0.2
    """PPO clip epsilon on ratios (Flow-GRPO, AWM). With one inner epoch the ratio is exactly 1 and the clip never
    binds; it matters only for inner_epochs > 1"""
    kl_beta: float = 0.0
    """weight of the KL to the reference policy (the base, adapters off, under c_E). WMSD's anchor (Eq. 11, to the
    Demonstrator under c_D) plays this part, so it is off by default"""
    timesteps: int = 2
    """AWM / NFT: re-noising times per final sample"""
    times: str = "uniform"
    """AWM / NFT: where the re-noising times lie -- uniform (in [0, 0.98)) | grid (the sampler's own step times, as
    the public trainer Flow-Factory draws them by default; Tab. 3 does not say). _renoise draws both"""
    weighting: str = "ghuber"
    """AWM time weighting: uniform | t | huber | ghuber (Tab. 3: ghuber)"""
    ghuber_power: float = 0.5
    """power p of the generalised Huber weighting (Tab. 3 does not give it; p = 0.5 is the Huber case; Flow-Factory,
    a public trainer with Tab. 3's setting names, defaults to 0.25)"""
    ratio: str = "exp_first"
    """AWM ratio: exp_first (one per (sample, time), Tab. 3) | sum_first (one per sample)"""
    nft_beta: float = 1.0
    """DiffusionNFT's step beta between the old velocity and the implicit policies"""
    adv_max: float = 5.0
    """DiffusionNFT's A_max, the advantage at which its optimality probability reaches 0 or 1. train.py sets it to
    its advantage clip (--adv_clip; 5 when that is 0, no clip), as the public trainer Flow-Factory divides by its
    clip bound, so the largest advantage the clip lets through counts as certain"""


def _reference(model, x, t, c):
    """v_ref(x, t | c): the base with adapters off -- Flow-GRPO's and AWM's reference policy. No gradient."""
    with torch.no_grad(), models.adapters_disabled(model):
        return model(x, t, c)


def _sq(a: torch.Tensor) -> torch.Tensor:
    """||a||^2 as a mean over all but the first dimension: (B, ...) -> (B,)."""
    return a.pow(2).flatten(1).mean(1)


def _ppo(ratio: torch.Tensor, A: torch.Tensor, eps: float) -> torch.Tensor:
    """The clipped surrogate, as a loss: max(-A r, -A clip(r, 1 - eps, 1 + eps)), elementwise."""
    return torch.maximum(-A * ratio, -A * ratio.clamp(1 - eps, 1 + eps))


# ----------------------------------------------------------------------------------------------------------------
# GRPO and Flow-GRPO: likelihoods of the SDE's Gaussian transitions
# ----------------------------------------------------------------------------------------------------------------

def _step_log_probs(model, ro: Rollouts, with_mean: bool = False):
    """log p_theta(x_{t_{k+1}} | x_{t_k}, c_E) of every recorded transition under the current parameters,
    (N, S); optionally the transitions' means mu_theta (S, N, ...) and stds s (S, N)."""
    S, N = ro.xs.shape[0] - 1, ro.xs.shape[1]
    t_min = float(ro.ts[1])
    lps, mus, ss = [], [], []
    for k in range(S):
        t = ro.ts[k].expand(N)
        _, lp, mu, s = flow.sde_step(model(ro.xs[k], t, ro.c), ro.xs[k], t, float(ro.ts[k + 1] - ro.ts[k]),
                                     ro.noise_level, t_min, x_next=ro.xs[k + 1])
        lps.append(lp)
        mus.append(mu)
        ss.append(s)
    lp = torch.stack(lps, 1)
    return (lp, torch.stack(mus), torch.stack(ss)) if with_mean else lp


def _per_step(A: torch.Tensor) -> torch.Tensor:
    """Advantages as (N, S) or broadcastable to it: per-rollout A (N,) -> (N, 1); per-step A (N, S) as it is."""
    return A if A.dim() == 2 else A[:, None]


def _per_sample(A: torch.Tensor, name: str) -> torch.Tensor:
    if A.dim() != 1:
        raise ValueError(f"{name} scores whole samples, not transitions: per-step advantages (App. A.3, "
                         "--distill_reward per_step) need a per-transition objective: grpo, flow-grpo, or awm "
                         "re-noising on the sampler's grid with exp_first")
    return A


def _need_sde(ro: Rollouts, name: str):
    if ro.log_probs is None:
        raise ValueError(f"{name} needs SDE rollouts with log-probs (flow.sample_sde); got ODE rollouts")


def grpo(model, ro: Rollouts, A: torch.Tensor, cfg: RLConfig, generator=None):
    """App. A.9 (GRPO [52]): L_GRPO = -E_T [ (1/G) sum_i A_i log p_theta(tau_i | T) ], with the rollout's
    log-likelihood the sum of its S Gaussian transitions' log-probs, log p(tau) = sum_k log p(x_{k+1} | x_k)
    (each a mean over dimensions, flow.sde_step). The plain policy gradient: no ratio, no clip. With per-step
    advantages A (N, S) (App. A.3) each transition k is weighted by its own A_k^i: -mean_i sum_k A_k^i log p_k^i."""
    _need_sde(ro, "grpo")
    lp = _step_log_probs(model, ro)                                     # (N, S)
    loss = -(_per_step(A) * lp).sum(1).mean()
    return loss, {"log_prob": lp.sum(1).mean().item()}


def gaussian_kl(mu_p: torch.Tensor, mu_q: torch.Tensor, s: torch.Tensor) -> torch.Tensor:
    """App. A.9 (Flow-GRPO's beta D_KL(pi_theta || pi_ref) per transition), in closed form:
    KL(N(mu_p, s^2 I) || N(mu_q, s^2 I)) = ||mu_p - mu_q||^2 / (2 s^2), mean over dimensions (matching the
    log-prob reduction). mu: (B, ...), s: (B,) -> (B,). Zero iff the means agree."""
    return _sq(mu_p - mu_q) / (2 * s.pow(2))


def flow_grpo(model, ro: Rollouts, A: torch.Tensor, cfg: RLConfig, generator=None):
    """App. A.9 (Flow-GRPO [40]): maximise

        J = E[ (1/G) sum_i (1/S) sum_k ( min(r_k^i A^i, clip(r_k^i, 1 - eps, 1 + eps) A^i)
                                           - beta KL(pi_theta || pi_ref) ) ],
        r_k^i = p_theta(x_{k+1}^i | x_k^i, c) / p_theta_old(x_{k+1}^i | x_k^i, c),

    with the old log-probs those recorded by the sampler (ro.log_probs) and the KL between the two Gaussian
    transitions in closed form (same std, so only the means differ: gaussian_kl). Returned as the loss -J.
    Per-step advantages A (N, S) (App. A.3) replace A^i by A_k^i in step k's term."""
    _need_sde(ro, "flow_grpo")
    lp, mu, s = _step_log_probs(model, ro, with_mean=True)             # (N, S), (S, N, ...), (S, N)
    ratio = (lp - ro.log_probs).exp()
    loss = _ppo(ratio, _per_step(A), cfg.clip_range).mean()
    info = {"ratio_mean": ratio.mean().item(), "clip_frac": ((ratio - 1).abs() > cfg.clip_range).float().mean().item()}
    if cfg.kl_beta > 0:
        N, kls = ro.xs.shape[1], []
        for k in range(len(s)):
            t = ro.ts[k].expand(N)
            _, _, mu_ref, _ = flow.sde_step(_reference(model, ro.xs[k], t, ro.c), ro.xs[k], t,
                                            float(ro.ts[k + 1] - ro.ts[k]), ro.noise_level, float(ro.ts[1]),
                                            x_next=ro.xs[k + 1])
            kls.append(gaussian_kl(mu[k], mu_ref, s[k]))
        kl = torch.stack(kls).mean()
        loss = loss + cfg.kl_beta * kl
        info["kl"] = kl.item()
    return loss, info


# ----------------------------------------------------------------------------------------------------------------
# AWM and DiffusionNFT: the flow-matching loss on re-noised final samples
# ----------------------------------------------------------------------------------------------------------------

def _renoise(ro: Rollouts, n_t: int, generator=None, times: str = "uniform"):
    """Re-noising draws for n_t times per final sample, held fixed across inner epochs (in ro.draws):
    t (n_t * N,) stratified so every inner epoch sees the same spread -- stratum j of n_t is u in [j/n_t, (j+1)/n_t),
    and t = 0.98 u ("uniform", over [0, 0.98)) or the sampler's step time t_k, k = floor(S u), of the S steps the
    rollout took ("grid": ro.ts[:-1], so only times the sampler evaluated the velocity at are trained) -- and fresh
    noise eps; x_t = (1 - t) eps + t x_1 (Eq. 2's path) and the flow-matching target u = x_1 - eps."""
    if "renoise" not in ro.draws:
        N = ro.x1.shape[0]
        off, total = ro.shard or (0, N)
        strata = (torch.arange(n_t)[:, None] + torch.rand(n_t, total, generator=generator)) / n_t    # (n_t, total)
        if times == "uniform":
            t = 0.98 * strata
        elif times == "grid":
            grid = ro.ts[:-1].cpu()                                                       # (S,) t_0 = 0, ..., t_{S-1}
            t = grid[(strata * len(grid)).long().clamp(max=len(grid) - 1)]
        else:
            raise ValueError(f"unknown re-noising times {times!r}; choose uniform or grid")
        t = t[:, off:off + N].reshape(-1).to(ro.x1.device)                         # drawn on the CPU generator
        eps = torch.randn(n_t, total, *ro.x1.shape[1:], generator=generator)[:, off:off + N].flatten(0, 1)
        eps = eps.to(ro.x1.device)
        x1 = ro.x1.repeat(n_t, *([1] * (ro.x1.dim() - 1)))
        ro.draws["renoise"] = (flow.interpolate(eps, x1, t), t, x1 - eps)
    return ro.draws["renoise"]


def awm_weight(err: torch.Tensor, t: torch.Tensor, kind: str, power: float = 0.5) -> torch.Tensor:
    """AWM's time weighting rho of the per-sample flow-matching error err = ||v_theta(x_t, t) - (x_1 - eps)||^2
    (mean over dimensions), so that log pi_hat(x_1 | c) ~ -rho(err, t) (App. A.9, [67]). With s = 1 - t, the noise
    level in AWM's own convention (t = 1 data here):

        uniform  rho = err            t     rho = s err           huber  rho = s sqrt(err)
        ghuber   rho = s ((err + 1e-10)^p - 1e-10^p) / p           (generalised Huber; p = 1 is `t`, p -> 0 log)

    The Huber forms grow slower than err, so a few samples with large errors do not dominate the update."""
    s = 1 - t
    if kind == "uniform":
        return err
    if kind == "t":
        return s * err
    if kind == "huber":
        return s * (err + 1e-10).sqrt()
    if kind == "ghuber":
        return s * ((err + 1e-10).pow(power) - 1e-10 ** power) / power
    raise ValueError(f"unknown AWM weighting {kind!r}; choose uniform, t, huber or ghuber")


def awm(model, ro: Rollouts, A: torch.Tensor, cfg: RLConfig, generator=None):
    """App. A.9 (Advantage Weighted Matching [67]). The final sample x_1 is the action; its log-likelihood is
    approximated by the negative (weighted) flow-matching loss at re-noised points x_t = (1 - t) eps + t x_1,

        log pi_hat_theta(x_1 | c) ~ -rho( ||v_theta(x_t, t | c) - (x_1 - eps)||^2, t ),

    the ratio pi_hat_theta / pi_hat_theta_old is formed either per (sample, time) and then clipped and averaged
    ("exp_first", Tab. 3) or from the time-averaged log-likelihoods, once per sample ("sum_first"), and the PPO
    loss max(-A r, -A clip(r)) is minimised. At ratio 1 its gradient is A grad rho: positive advantages lower the
    flow-matching loss of good samples, negative ones raise it for bad ones. Optional velocity-space KL to the
    reference (the base under c_E): kl_beta ||v_theta - v_ref||^2. Works on ODE or SDE rollouts (only x_1 is used).
    Per-step advantages A (N, S) (App. A.3) need re-noising on the sampler's grid and exp_first: the term at
    t = t_k, which trains the velocity the sampler's transition k reads, takes that transition's A_k^i."""
    N, n_t = ro.x1.shape[0], cfg.timesteps
    if A.dim() == 2 and (cfg.times != "grid" or cfg.ratio != "exp_first"):
        _per_sample(A, "awm with uniform re-noising times or sum_first")
    x_t, t, u = _renoise(ro, n_t, generator, cfg.times)
    if A.dim() == 2:        # the grid index k of each re-noised time (t is one of ro.ts[:-1] exactly): A_k^i, (n_t, N)
        k = torch.searchsorted(ro.ts[:-1].contiguous(), t.contiguous()).reshape(n_t, N)
        A = A.T.gather(0, k)
    else:
        A = A[None]
    c = {k: v.repeat(n_t, *([1] * (v.dim() - 1))) for k, v in ro.c.items()}
    v = model(x_t, t, c)
    logp = -awm_weight(_sq(v - u), t, cfg.weighting, cfg.ghuber_power).reshape(n_t, N)    # (n_t, N)
    if "awm_old" not in ro.draws:                                # theta_old = theta at the first inner epoch
        ro.draws["awm_old"] = logp.detach()
    old = ro.draws["awm_old"]
    if cfg.ratio == "exp_first":
        ratio = (logp - old).exp()                                                         # (n_t, N)
        loss = _ppo(ratio, A, cfg.clip_range).mean()
    elif cfg.ratio == "sum_first":
        ratio = (logp.mean(0) - old.mean(0)).exp()                                         # (N,)
        loss = _ppo(ratio, A[0], cfg.clip_range).mean()
    else:
        raise ValueError(f"unknown AWM ratio {cfg.ratio!r}; choose exp_first or sum_first")
    info = {"fm_err": (-logp).mean().item(), "ratio_mean": ratio.mean().item()}
    if cfg.kl_beta > 0:
        kl = _sq(v - _reference(model, x_t, t, c)).mean()
        loss = loss + cfg.kl_beta * kl
        info["kl"] = kl.item()
    return loss, info


def nft(model, ro: Rollouts, A: torch.Tensor, cfg: RLConfig, generator=None):
    """Sec. 3's third approach to L_RL, DiffusionNFT [71] (online RL with the forward process). Each final sample
    gets an optimality probability r = 1/2 + 1/2 clip(A / A_max, -1, 1), A_max = cfg.adv_max (the advantage clip,
    `advantages`, train.py --adv_clip). Around the old velocity v_old = sg(v_theta_old) two implicit policies are
    formed,

        v+ = (1 - beta) v_old + beta v_theta,        v- = (1 + beta) v_old - beta v_theta,

    and trained with the flow-matching loss on the forward process x_t = (1 - t) eps + t x_1, target u = x_1 - eps:

        L_NFT = E[ r ||v+(x_t, t) - u||^2 + (1 - r) ||v-(x_t, t) - u||^2 ].

    Good samples pull v+ (and so v_theta) towards their flow, bad ones push v- towards theirs -- i.e. v_theta away.
    No likelihood and no sampler in the loss: any sampler can produce x_1."""
    n_t, A = cfg.timesteps, _per_sample(A, "nft")
    x_t, t, u = _renoise(ro, n_t, generator, cfg.times)
    c = {k: v.repeat(n_t, *([1] * (v.dim() - 1))) for k, v in ro.c.items()}
    v = model(x_t, t, c)
    if "nft_old" not in ro.draws:
        ro.draws["nft_old"] = v.detach()
    v_old, b = ro.draws["nft_old"], cfg.nft_beta
    r = (0.5 + 0.5 * (A / cfg.adv_max).clamp(-1, 1)).repeat(n_t)
    pos, neg = (1 - b) * v_old + b * v, (1 + b) * v_old - b * v
    loss = (r * _sq(pos - u) + (1 - r) * _sq(neg - u)).mean()
    return loss, {"fm_err": _sq(v.detach() - u).mean().item()}


OBJECTIVES = {"awm": awm, "flow-grpo": flow_grpo, "grpo": grpo, "nft": nft}
NEEDS_SDE = ("flow-grpo", "grpo")
