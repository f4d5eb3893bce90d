"""Rectified flow: the linear path, its training loss, and the Euler ODE sampler (Sec. 3 Eq. 2, App. A.9).

Time convention (the paper's, used everywhere in this repository): t = 0 is noise, t = 1 is data,

    x_t = (1 - t) x_0 + t x_1,      x_0 ~ N(0, I),  x_1 ~ p_data,      d x_t / dt = x_1 - x_0.

A velocity field v(x_t, t) is any callable (x: (B, ...), t: (B,)) -> (B, ...). Conditioning (first frame, text)
is closed over by the caller; guided_field combines two such fields (classifier-free guidance). Where a real model
uses the other convention (diffusers' sigma = 1 - t, LTX-2), the conversion happens in models.py at that boundary
only.
"""
from __future__ import annotations

import math
from typing import Callable

import torch

VelocityField = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


def _bcast(t: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
    """(B,) -> (B, 1, ..., 1) to broadcast against x."""
    return t.reshape(-1, *([1] * (x.dim() - 1)))


def interpolate(x_0: torch.Tensor, x_1: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Eq. 2's probability path (App. A.9): x_t = (1 - t) x_0 + t x_1.  x_0, x_1: (B, ...), t: (B,)."""
    t = _bcast(t, x_0)
    return (1 - t) * x_0 + t * x_1


def flow_matching_loss(v_theta: VelocityField, x_0: torch.Tensor, x_1: torch.Tensor, t: torch.Tensor,
                       weight: torch.Tensor | None = None) -> torch.Tensor:
    """App. A.9: L_FM(theta) = E_{x_0, x_1, t} || v_theta(x_t, t) - (x_1 - x_0) ||^2.

    Reduction: the squared error is averaged over all elements (pixels, channels, frames) and the batch, so the
    loss does not grow with the video size. `weight` optionally weights each sample, shape (B,), or each element,
    shape broadcastable to x_1; a positive weight keeps the minimiser, the conditional expectation
    E[x_1 - x_0 | x_t], and changes only where the model spends its capacity."""
    x_t = interpolate(x_0, x_1, t)
    err = (v_theta(x_t, t) - (x_1 - x_0)).pow(2)  # (B, ...)
    if weight is not None:
        err = err * (_bcast(weight, err) if weight.dim() == 1 else weight)
    return err.mean()


def time_grid(steps: int, device=None) -> torch.Tensor:
    """The sampler's grid for Eq. 2 (App. A.9): uniform 0 = t_0 < t_1 < ... < t_steps = 1, shape (steps + 1,)."""
    return torch.linspace(0.0, 1.0, steps + 1, device=device)


def sample_ode(v_theta: VelocityField, x_0: torch.Tensor, steps: int, return_trajectory: bool = False):
    """Integrate Eq. 2, d x_t / dt = v_theta(x_t, t), from t = 0 (noise) to t = 1 (data) with Euler steps:

        x_{t_{k+1}} = x_{t_k} + (t_{k+1} - t_k) v_theta(x_{t_k}, t_k),    k = 0 .. steps - 1.

    Returns x_1 (B, ...), or with return_trajectory=True the pair (xs, ts): xs (steps + 1, B, ...) holds every
    state x_{t_0} .. x_{t_steps} and ts (steps + 1,) their times -- the states on-policy losses and rewards use.
    Gradients flow through the sampler only if the caller enables them; wrap in torch.no_grad() for rollouts."""
    ts = time_grid(steps, x_0.device)
    x, xs = x_0, [x_0]
    for k in range(steps):
        t = ts[k].expand(x.shape[0])
        x = x + (ts[k + 1] - ts[k]) * v_theta(x, t)
        if return_trajectory:
            xs.append(x)
    return (torch.stack(xs), ts) if return_trajectory else x


def guided_field(v_cond: VelocityField, v_uncond: VelocityField, scale: float) -> VelocityField:
    """Classifier-free guidance (Ho & Salimans, 2022; not in the paper, which does not say whether it guides): the
    field that Eq. 2's sampler integrates becomes

        v_w(x_t, t) = v(x_t, t | c_u) + w (v(x_t, t | c) - v(x_t, t | c_u)),

    c the prompt's conditioning and c_u the same first frame with an empty caption (the toy base read one in a tenth
    of its pretraining clips, train.py --p_empty). w = 1 returns v(x_t, t | c) itself, w = 0 the caption-free field;
    any other w costs two forwards a step instead of one."""
    if scale == 1:
        return v_cond

    def v_w(x: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        v_u = v_uncond(x, t)
        return v_u + scale * (v_cond(x, t) - v_u)
    return v_w


# ----------------------------------------------------------------------------------------------------------------
# the SDE sampler for exploration (App. A.9, Flow-GRPO), with per-step Gaussian log-probabilities
# ----------------------------------------------------------------------------------------------------------------

def sde_sigma(t: torch.Tensor, noise_level: float, t_min: float) -> torch.Tensor:
    """App. A.9 (Flow-GRPO [40]): the SDE's diffusion coefficient sigma_t of dx = (...) dt + sigma_t dw, in our
    convention sigma_t = a sqrt((1 - t) / t), a = noise_level.
    (Flow-GRPO writes sqrt(s / (1 - s)) with s = 1 - t its noise level.) It diverges at t = 0, where the state is
    pure noise, so t is clamped to t_min >= the sampler's first step (Flow-GRPO likewise uses its second sigma)."""
    t = t.clamp(min=t_min)
    return noise_level * ((1 - t) / t).sqrt()


def sde_step(v: torch.Tensor, x: torch.Tensor, t: torch.Tensor, dt: float, noise_level: float, t_min: float,
             x_next: torch.Tensor | None = None, generator: torch.Generator | None = None):
    """One Euler-Maruyama step of the SDE with Eq. 2's marginals (App. A.9, Flow-GRPO):

        dx = [v_t(x) + (sigma_t^2 / 2) grad log p_t(x)] dt + sigma_t dw,
        grad log p_t(x) = -(x - t v_t(x)) / (1 - t)          (the noise estimate x_0_hat = x - t v over its scale),

    so the transition is Gaussian, x_next ~ N(mu, s^2 I) with

        mu = x + dt [v - sigma_t^2 (x - t v) / (2 (1 - t))],      s = sigma_t sqrt(dt).

    (With time running 0 -> 1 the score term enters with a plus sign; the Fokker-Planck terms of the score drift
    and of the noise cancel, so every sigma_t gives the ODE's marginals.) v: v_theta(x, t), (B, ...); t: (B,).
    If x_next is None it is drawn; otherwise its log-probability is evaluated (recomputing log-probs of recorded
    transitions under new parameters). Returns (x_next, log_prob (B,), mu, s (B,)).

    Reduction: log_prob is the Gaussian log-density *averaged* over latent dimensions, as Flow-GRPO does. The sum
    over d dimensions would make log-ratios d times larger -- per-step ratios of exp(+-1000) on a video -- so the
    clip range would have to shrink with the video size; the mean keeps ratios near 1 and one clip range (and KL
    weight) across sizes. The average is the sum / d, a fixed temperature; its gradient has the same direction."""
    sig = sde_sigma(t, noise_level, t_min)
    tb, sb = _bcast(t, x), _bcast(sig, x)
    mu = x + dt * (v - sb.pow(2) * (x - tb * v) / (2 * (1 - tb)))
    s = sig * dt ** 0.5                                                      # (B,)
    if x_next is None:
        x_next = mu + _bcast(s, x) * torch.randn(x.shape, generator=generator, device=x.device)
    z2 = ((x_next.detach() - mu) / _bcast(s, x)).pow(2)
    log_prob = (-0.5 * z2 - _bcast(s.log(), x) - 0.5 * math.log(2 * math.pi)).flatten(1).mean(1)
    return x_next, log_prob, mu, s


def sample_sde(v_theta: VelocityField, x_0: torch.Tensor, steps: int, noise_level: float = 0.7,
               generator: torch.Generator | None = None, noises: torch.Tensor | None = None):
    """App. A.9 (Flow-GRPO [40]): denoising as a multi-step MDP,
    a_k = x_{t_{k+1}} ~ pi_theta(. | s_k = (c, t_k, x_{t_k})). Rolls out the SDE of sde_step on the uniform grid
    from t = 0 to t = 1. Returns (xs (steps + 1, B, ...), ts (steps + 1,), log_probs (B, steps)): every state and
    the log-probability of every transition x_{t_k} -> x_{t_{k+1}} under the policy that drew it (Flow-GRPO's old
    log-probs). noise_level = 0 would be the ODE, but the Gaussian has no density then; use sample_ode. Wrap in
    torch.no_grad() for rollouts. `noises` (steps, B, ...): the standard normal draws to use instead of drawing
    them (a multi-process run draws them for the whole batch and gives each process its slice, so it samples what
    one process would)."""
    if noise_level <= 0:
        raise ValueError("sample_sde needs noise_level > 0 (noise_level 0 is the ODE: use sample_ode)")
    ts = time_grid(steps, x_0.device)
    x, xs, lps = x_0, [x_0], []
    for k in range(steps):
        t = ts[k].expand(x.shape[0])
        v, dt = v_theta(x, t), float(ts[k + 1] - ts[k])
        x_next = None
        if noises is not None:   # the same arithmetic as sde_step's own draw
            _, _, mu, s = sde_step(v, x, t, dt, noise_level, float(ts[1]), x_next=x)
            x_next = mu + _bcast(s, x) * noises[k]
        x, lp, _, _ = sde_step(v, x, t, dt, noise_level, float(ts[1]), x_next=x_next, generator=generator)
        xs.append(x)
        lps.append(lp)
    return torch.stack(xs), ts, torch.stack(lps, 1)
