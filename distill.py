"""Self-distillation of the Demonstrator into the Executor (Sec. 3, Eqs. 3-6, 9, 11; App. A.2.1, A.3, A.10).

The Executor is v_theta(x_t, t | c_E) with c_E = (first frame, short task T): the base model with LoRA on.
The Demonstrator is v_theta'(x_t, t | c_D) with c_D = (first frame, description D): the same base with the
adapters off (models.adapters_disabled) -- fixed, never trained (App. A.3: a moving Demonstrator was unstable).

Every objective takes a `model` that is both (adapters on = Executor, off = Demonstrator), conditions c_E and c_D
as returned by model.condition(...), and states on a trajectory (xs, ts) as returned by flow.sample_ode(...,
return_trajectory=True) through `rollout`. The integral over t in Eqs. 5, 6, 9, 11 becomes a left Riemann sum on
the sampler's grid, sum_k (t_{k+1} - t_k) f(x_{t_k}, t_k) -- the states the sampler actually visited -- or, for
the losses, an unbiased one-point estimate at a random grid index per sample.

Reduction: ||.||^2 in the paper is a sum over latent dimensions; here it is a *mean* over them (pixels, channels,
frames), so losses and r_distill do not scale with video size. That is the sum divided by d, a constant factor
absorbed by beta_d and lambda_distill.

Simplifications: the DMD generator G_theta(z, c_E) is the Executor's clean estimate from a random state of its own
no-grad trajectory from z (`dmd_generator`: one network call carries the gradient, DMD2's "backward simulation");
its fake score is a LoRA copy of the base.
"""
from __future__ import annotations

import contextlib
import copy

import torch

import flow
import models


# ----------------------------------------------------------------------------------------------------------------
# rollouts and the per-state discrepancy
# ----------------------------------------------------------------------------------------------------------------

@torch.no_grad()
def rollout(model, x_0: torch.Tensor, c: dict, steps: int, demonstrator: bool = False, velocities: bool = False,
            teacher=None):
    """A trajectory of Eq. 2 from noise x_0 (B, ...): the Executor's (adapters on) or, with demonstrator=True, the
    Demonstrator's -- `model` with adapters off, or the separate network `teacher` where one is given (as in
    teacher_velocity). Returns (xs (steps + 1, B, ...), ts (steps + 1,)); no gradient (Eq. 11's
    sg(x_t): sampled states are data, not functions of theta). With velocities=True, ((xs, ts), vs): also the
    velocity the sampler took at each grid state, vs (steps, B, ...). On the Demonstrator's trajectory under c_D
    those are Eq. 3's targets v_theta'(x_{t_k}, t_k | c_D), which off_policy_loss then reads (its teacher_v) instead
    of running the Demonstrator again at the state it draws: the same numbers, one network call fewer a step."""
    if teacher is not None and not demonstrator:
        raise ValueError("a teacher is the Demonstrator: give demonstrator=True with it")
    net, vs = (teacher if teacher is not None else model), []

    def v(x, t):
        out = net(x, t, c)
        if velocities:
            vs.append(out)
        return out

    with models.adapters_disabled(model) if demonstrator and teacher is None else contextlib.nullcontext():
        traj = flow.sample_ode(v, x_0, steps, return_trajectory=True)
    return (traj, torch.stack(vs)) if velocities else traj


def teacher_velocity(model, x_t: torch.Tensor, t: torch.Tensor, c_D: dict, teacher=None) -> torch.Tensor:
    """v_theta'(x_t, t | c_D) of Eqs. 3, 4, 9, 11: the Demonstrator's velocity, a fixed target (no gradient).
    The Demonstrator is `model` with adapters off -- or a separate network `teacher`: Alg. 2's separately trained
    phi (its own adapters on), or the frozen base beside an Executor that trains every weight (train.py
    --executor_weights all)."""
    with torch.no_grad(), (models.adapters_disabled(model) if teacher is None else contextlib.nullcontext()):
        return (model if teacher is None else teacher)(x_t, t, c_D)


def discrepancy(model, x_t: torch.Tensor, t: torch.Tensor, c_E: dict, c_D: dict, teacher=None,
                motion_weight: float = 1.0) -> torch.Tensor:
    """Eq. 4: l_theta(x_t, t; c_E, c_D) = || v_theta(x_t, t | c_E) - v_theta'(x_t, t | c_D) ||^2.
    x_t (B, ...), t (B,) -> (B,), mean over latent dimensions (see the module docstring). Gradient flows into the
    Executor's velocity only; the Demonstrator's is a target. motion_weight: see `squared_error`."""
    return squared_error(model(x_t, t, c_E), teacher_velocity(model, x_t, t, c_D, teacher), x_t, t, c_D,
                         motion_weight)


def squared_error(v_E: torch.Tensor, v_D: torch.Tensor, x_t: torch.Tensor, t: torch.Tensor, c_D: dict,
                  motion_weight: float = 1.0) -> torch.Tensor:
    """Eq. 4's || v_E - v_D ||^2 as a mean over latent dimensions, (B,). With motion_weight w != 1 (ours, not the
    paper's; toy model only, train.py --distill_motion_weight) a pixel the Demonstrator moves weighs w times the
    others, as pretraining weighs moving pixels (models.moving_pixel_weight): a pixel whose Demonstrator clean
    estimate x̂_1 = x_t + (1 - t) v_D differs from the first frame."""
    d = (v_E - v_D).pow(2)
    if motion_weight != 1.0:
        x_hat = x_t + flow._bcast(1 - t, x_t) * v_D                     # the Demonstrator's clean estimate of x_1
        d = d * models.moving_pixel_weight(x_hat, c_D["frame0"], motion_weight)
    return d.flatten(1).mean(1)


def _pick_states(xs: torch.Tensor, ts: torch.Tensor, generator: torch.Generator | None = None,
                 shard: tuple | None = None, window: tuple | None = None):
    """One random grid state per sample: k ~ U{0 .. S-1} (the final state t = 1 is never an input of the sampler).
    xs (S+1, B, ...) -> x (B, ...), t (B,). shard = (offset, total): these B samples are rows offset.. of a batch of
    `total` split across processes; k is drawn for the whole batch and sliced (rl.Rollouts.shard).
    window = (lo, hi): k uniform over the grid steps with lo <= t_k < hi only (train.py --state_window;
    docs/given-t.md's flow windows). Without one the draws are the same as with window (0, 1)."""
    k = _pick_index(xs, ts, generator, shard, window)
    return xs[k, torch.arange(xs.shape[1], device=xs.device)].detach(), ts[k]


def _pick_index(xs, ts, generator=None, shard=None, window=None) -> torch.Tensor:
    """_pick_states's grid index k per sample, (B,)."""
    S, B = xs.shape[0] - 1, xs.shape[1]
    off, total = shard or (0, B)
    ks = torch.arange(S)
    if window is not None:
        t_grid = ts[:-1].detach().cpu()
        ks = ks[(t_grid >= window[0] - 1e-6) & (t_grid < window[1] - 1e-6)]
        if len(ks) == 0:
            raise ValueError(f"no grid time t_k of {S} steps lies in the state window [{window[0]}, {window[1]})")
    return ks[torch.randint(0, len(ks), (total,), generator=generator)][off:off + B].to(xs.device)


@torch.no_grad()
def teacher_velocities(model, traj, c_D: dict, teacher=None) -> torch.Tensor:
    """v_theta'(x_{t_k}, t_k | c_D) at every grid state k = 0 .. S-1 of a trajectory (xs, ts): (S, B, ...). Eq. 9
    needs them all; Eq. 11's one-point estimate then reads its state's from them (anchor_loss's teacher_v) instead of
    running the Demonstrator again -- the same numbers, one forward fewer a step."""
    xs, ts = traj
    return torch.stack([teacher_velocity(model, xs[k], ts[k].expand(xs.shape[1]), c_D, teacher)
                        for k in range(xs.shape[0] - 1)])


# ----------------------------------------------------------------------------------------------------------------
# off-policy (Eq. 3), on-policy (Eq. 5), anchor (Eq. 11)
# ----------------------------------------------------------------------------------------------------------------

def off_policy_loss(model, teacher_traj, c_E: dict, c_D: dict, generator=None, teacher=None,
                    shard: tuple | None = None, window: tuple | None = None, motion_weight: float = 1.0,
                    teacher_v: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 3: L_off = E_{(x_t, t) ~ p_theta'(. | c_D)} || v_theta(x_t, t | c_E) - v_theta'(x_t, t | c_D) ||^2.
    `teacher_traj` = rollout(model, x_0, c_D, steps, demonstrator=True): states the *Demonstrator* visits, which do
    not depend on theta -- stable, but the Executor is only taught where the teacher goes. `teacher_v`: the
    Demonstrator's velocities along that trajectory, which its sampler computed (rollout(..., velocities=True)).
    Scalar."""
    return _at_drawn_states(model, teacher_traj, c_E, c_D, generator, teacher, shard, window, motion_weight,
                            teacher_v)


def anchor_loss(model, student_traj, c_E: dict, c_D: dict, generator=None, teacher=None,
                shard: tuple | None = None, window: tuple | None = None, motion_weight: float = 1.0,
                teacher_v: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 11:

        L_anchor = E_{tau ~ p_theta(. | c_E)} int_0^1 || v_theta(x̄_t, t | c_E) - v_theta'(x̄_t, t | c_D) ||^2 dt,

    x̄_t = sg(x_t). `student_traj` = rollout(model, x_0, c_E, steps): states the *Executor* visits, detached, so no
    gradient reaches the sampler. `teacher_v`: the Demonstrator's velocities along the trajectory
    (teacher_velocities), if already computed for Eq. 9. Scalar."""
    return _at_drawn_states(model, student_traj, c_E, c_D, generator, teacher, shard, window, motion_weight,
                            teacher_v)


def _at_drawn_states(model, traj, c_E, c_D, generator, teacher, shard, window, motion_weight, teacher_v):
    """The one-point estimate Eqs. 3 and 11 share, on whichever trajectory (xs, ts) they are given: Eq. 4's
    l_theta at one grid state drawn per sample (_pick_index; with `window`, of the integral over [lo, hi) only, up
    to the factor hi - lo), the state detached, averaged over the batch. The Demonstrator's velocity there is
    teacher_v[k] where the caller has it, else computed."""
    xs, ts = traj
    k, rows = _pick_index(xs, ts, generator, shard, window), torch.arange(xs.shape[1], device=xs.device)
    x_t, t = xs[k, rows].detach(), ts[k]
    v_D = teacher_velocity(model, x_t, t, c_D, teacher) if teacher_v is None else teacher_v[k, rows]
    return squared_error(model(x_t, t, c_E), v_D, x_t, t, c_D, motion_weight).mean()   # Eq. 4's l_theta


def on_policy_loss(model, student_traj, c_E: dict, c_D: dict, generator=None,
                   window: tuple | None = None, motion_weight: float = 1.0, teacher=None) -> torch.Tensor:
    """Eq. 5: L_on = E_{(x_t, t) ~ p_theta(. | c_E)} l_theta(x_t, t) = E_tau int_0^1 l_theta(x_t, t) dt, on the
    Executor's own states, with C_theta(tau) = int_0^1 l_theta(x_t, t) dt the trajectory's cost (Eq. 6). Its
    gradient has two terms (Eq. 7): a score-function term E[C_theta(tau) grad log p_theta(tau)] that moves the
    state distribution, and a direct regression term E[grad C_theta(tau)]. Backpropagating through the sampler is
    impractical, so on sampled states held fixed this returns the direct term only -- which is exactly the anchor
    of Eq. 11. The score-function term is what RL with r_distill (Eq. 9) adds."""
    return anchor_loss(model, student_traj, c_E, c_D, generator, teacher, window=window, motion_weight=motion_weight)


# ----------------------------------------------------------------------------------------------------------------
# the distillation reward (Eq. 9, and the per-step form of App. A.3)
# ----------------------------------------------------------------------------------------------------------------

@torch.no_grad()
def distill_reward(model, student_traj, c_E: dict, c_D: dict, per_step: bool = False,
                   student_v: torch.Tensor | None = None, teacher=None, motion_weight: float = 1.0,
                   teacher_v: torch.Tensor | None = None) -> torch.Tensor:
    """Eq. 9: r_distill(tau) = - int_0^1 || sg[v_theta(x_t, t | c_E)] - v_theta'(x_t, t | c_D) ||^2 dt
    on an Executor trajectory, as the left Riemann sum on the sampler's grid:

        r_distill = - sum_{k=0}^{S-1} (t_{k+1} - t_k) l(x_{t_k}, t_k).

    Returns (B,); with per_step=True the (B, S) terms -(t_{k+1} - t_k) l(x_{t_k}, t_k) of App. A.3 (their sum is the
    trajectory reward). No gradient: it acts through trajectory likelihood in the RL loss, not by backprop.
    `student_v` (S, B, ...): the Executor's velocities v_theta(x_{t_k}, t_k | c_E) recorded while sampling, which
    spares recomputing them (only the Demonstrator's are then evaluated); `teacher_v` (S, B, ...): the
    Demonstrator's, from teacher_velocities."""
    xs, ts = student_traj
    S, B = xs.shape[0] - 1, xs.shape[1]
    terms = []
    for k in range(S):
        t = ts[k].expand(B)
        v_E = model(xs[k], t, c_E) if student_v is None else student_v[k]
        v_D = teacher_velocity(model, xs[k], t, c_D, teacher) if teacher_v is None else teacher_v[k]
        l_k = squared_error(v_E, v_D, xs[k], t, c_D, motion_weight)             # Eq. 4's l_theta
        terms.append(-(ts[k + 1] - ts[k]) * l_k)
    terms = torch.stack(terms, dim=1)  # (B, S)
    return terms if per_step else terms.sum(1)


def distill_reward_to_go(terms: torch.Tensor) -> torch.Tensor:
    """App. A.3's per-step distillation reward as the credit of each transition of the sampler. The transition
    x_{t_k} -> x_{t_{k+1}} (the SDE's action a_k, App. A.9) can change only the states after it, so it is credited
    with the per-step terms of Eq. 9 from step k + 1 on,

        G_k = sum_{j=k+1}^{S-1} r_j,      r_j = -(t_{j+1} - t_j) l(x_{t_j}, t_j)      (distill_reward(per_step=True)),

    where the trajectory-level form credits every transition with all of sum_j r_j, the terms before it included.
    terms (B, S) -> (B, S). G_{S-1} = 0: the last transition makes x_1, where the Riemann sum has no term; r_0, at
    the pure noise x_0, credits no transition."""
    to_go = terms.flip(1).cumsum(1).flip(1)                  # sum_{j >= k} r_j
    return torch.cat([to_go[:, 1:], torch.zeros_like(to_go[:, :1])], 1)


# ----------------------------------------------------------------------------------------------------------------
# the DMD variant (App. A.2.1, Eqs. 13-22)
# ----------------------------------------------------------------------------------------------------------------

def make_fake_score(model, rank: int = 8, alpha: float = 16.0):
    """The fake-score denoiser mu_fake^phi of Eq. 17: a copy of the base with its own fresh LoRA (B = 0, so it
    starts equal to the Demonstrator's network), trained online on Executor samples by Eq. 18."""
    fake = copy.deepcopy(model)
    for m in fake.modules():  # fold any Executor adapters away: phi starts from the base weights
        if isinstance(m, models.LoRA):
            m.lora_B.data.zero_()
    if not any(isinstance(m, models.LoRA) for m in fake.modules()):
        models.add_lora(fake, rank, alpha)
    for n, p in fake.named_parameters():
        p.requires_grad_("lora_" in n)
    return fake


def dmd_generator(model, student_traj, c_E: dict, generator=None) -> torch.Tensor:
    """G_theta(z, c_E) of Eqs. 21-22 for a multi-step Executor: the paper's G_theta is a one-step generator; ours
    samples in S Euler steps, so, as DMD2 does for multi-step students (Yin et al. 2024, "backward simulation"),

        x = G_theta(z, c_E) = mu_theta(x̄_k, t_k | c_E) = x̄_k + (1 - t_k) v_theta(x̄_k, t_k | c_E),

    the Executor's clean-video estimate at a random grid state x̄_k = sg(x_{t_k}) of its own trajectory from z
    (`student_traj` = rollout(model, z, c_E, steps)). k = 0 is the literal one-step generator from noise. The
    gradient flows through this one network call (measured on the toy: 100 steps took 5.9 min when it flowed
    through all 10 Euler steps). Returns x (B, ...) with gradient."""
    x_k, t_k = _pick_states(*student_traj, generator)
    return _denoise(model, x_k, t_k, c_E)


def _denoise(model, x_t, t, c):
    """mu(x_t, t) = x_t + (1 - t) v(x_t, t): the clean-data estimate in our convention (t = 1 is data)."""
    return x_t + flow._bcast(1 - t, x_t) * model(x_t, t, c)


def dmd_generator_loss(model, fake, x: torch.Tensor, c_E: dict, c_D: dict, generator=None) -> torch.Tensor:
    """DMD minimises D_KL(p_fake || p_real) = E_{x ~ p_fake}[log p_fake(x) / p_real(x)] (Eq. 13), whose gradient
    is E_z[-(s_real(x) - s_fake(x)) dG_theta(z)/dtheta] (Eq. 14); here p_fake is the Executor's p_theta(. | c_E) and
    p_real the Demonstrator's p_theta'(. | c_D), the KL of Eq. 20. Eqs. 19/21 estimate that gradient on noisy
    samples: the Executor's samples x = G_theta(z, c_E) (with gradient) are re-noised by Eq. 15,
    q_t(x_t | x) = N(alpha_t x, sigma_t^2 I) with alpha_t = t, sigma_t = 1 - t in our convention, and pushed along

        grad_theta D_KL ~ E[ w_t alpha_t (s_fake(x_t, t | c_E) - s_real(x_t, t | c_D)) dG/dtheta ],
        s(x_t) = -(x_t - alpha_t mu(x_t, t)) / sigma_t^2                                     (Eqs. 16, 17)

    so s_fake - s_real = alpha_t (mu_fake - mu_real) / sigma_t^2. The real score is the Demonstrator under c_D
    (adapters off), the fake one `fake` under c_E. w_t = sigma_t^2 / (alpha_t^2 mean|x - mu_real|), DMD's
    normalisation (Yin et al. 2024), makes the step (mu_fake - mu_real) / mean|x - mu_real|. Returned as the
    surrogate 0.5 ||x - sg(x - g)||^2 (mean over elements), whose gradient w.r.t. x is g."""
    B = x.shape[0]
    t = torch.rand(B, generator=generator).clamp(0.02, 0.98)
    eps = torch.randn(x.shape, generator=generator)
    with torch.no_grad():
        x_t = flow.interpolate(eps, x.detach(), t)                # alpha_t x + sigma_t eps
        with models.adapters_disabled(model):
            mu_real = _denoise(model, x_t, t, c_D)
        mu_fake = _denoise(fake, x_t, t, c_E)
        norm = flow._bcast((x.detach() - mu_real).abs().flatten(1).mean(1).clamp(min=1e-3), x)
        g = (mu_fake - mu_real) / norm
    return 0.5 * (x - (x - g).detach()).pow(2).mean()


def dmd_fake_score_loss(fake, x: torch.Tensor, c_E: dict, generator=None) -> torch.Tensor:
    """Eq. 18: L_denoise^phi = || mu_fake^phi(x_t, t) - x ||^2 on detached Executor samples x, x_t ~ q_t(. | x).
    Mean over elements and batch."""
    B = x.shape[0]
    t = torch.rand(B, generator=generator).clamp(0.02, 0.98)
    x_t = flow.interpolate(torch.randn(x.shape, generator=generator), x.detach(), t)
    return (_denoise(fake, x_t, t, c_E) - x.detach()).pow(2).mean()
