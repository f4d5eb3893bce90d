"""Rectified flow: the linear path, its training loss, and the Euler ODE sampler (Sec. 3 Eq. 2, App. A.9).

Time convention (the paper's, used everywhere in this repository): t = 0 is noise, t = 1 is data,

    x_t = (1 - t) x_0 + t x_1,      x_0 ~ N(0, I),  x_1 ~ p_data,      d x_t / dt = x_1 - x_0.

A velocity field v(x_t, t) is any callable (x: (B, ...), t: (B,)) -> (B, ...). Conditioning (first frame, text)
is closed over by the caller. Where a real model uses the other convention (diffusers' sigma = 1 - t, LTX-2),
the conversion happens in models.py at that boundary only.
"""
from __future__ import annotations

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
