"""Volume-rendering quadrature (NeRF / the paper's eq. 1) as pure functions.

Samples along R rays: `t` [R, S] sorted distances, `sigma` [R, S] densities. Then
delta_i = t_{i+1} - t_i (the last one gets `far_delta`), alpha_i = 1 - exp(-sigma_i delta_i),
T_i = prod_{j<i} (1 - alpha_j), w_i = T_i alpha_i, opacity O = sum w_i, depth = sum w_i t_i.
`composite` applies one set of weights to any per-sample channels ([R, S, C] -> [R, C]), so dual
rendering (template + modification colours) and feature channels reuse the same weights.
"""

from __future__ import annotations

import torch


def deltas(t: torch.Tensor, far_delta: float = 1e10) -> torch.Tensor:
    """Sample spacings [R, S] from sorted sample distances t [R, S]."""
    last = torch.full_like(t[..., :1], far_delta)
    return torch.cat([t[..., 1:] - t[..., :-1], last], dim=-1)


def alphas(sigma: torch.Tensor, delta: torch.Tensor) -> torch.Tensor:
    """Per-sample opacity alpha = 1 - exp(-sigma * delta), [R, S]."""
    return 1.0 - torch.exp(-sigma * delta)


def transmittance(alpha: torch.Tensor) -> torch.Tensor:
    """T_i = prod_{j<i} (1 - alpha_j), [R, S] (exclusive cumulative product, T_0 = 1)."""
    ones = torch.ones_like(alpha[..., :1])
    return torch.cumprod(torch.cat([ones, 1.0 - alpha[..., :-1] + 1e-10], dim=-1), dim=-1)


def weights_from_alpha(alpha: torch.Tensor) -> torch.Tensor:
    """w_i = T_i alpha_i, [R, S]."""
    return transmittance(alpha) * alpha


def render_weights(
    sigma: torch.Tensor, t: torch.Tensor, far_delta: float = 1e10, delta: torch.Tensor | None = None
) -> torch.Tensor:
    """Weights [R, S] from densities [R, S] at sorted distances t [R, S] (or explicit deltas)."""
    if delta is None:
        delta = deltas(t, far_delta)
    return weights_from_alpha(alphas(sigma, delta))


def composite(weights: torch.Tensor, channels: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Per-sample channels {name: [R, S, C]} -> per-ray {name: [R, C]} = sum_i w_i c_i."""
    return {k: (weights[..., None] * v).sum(dim=-2) for k, v in channels.items()}


def opacity(weights: torch.Tensor) -> torch.Tensor:
    """Accumulated opacity O = sum_i w_i, [R]."""
    return weights.sum(dim=-1)


def expected_depth(weights: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """Expected ray distance sum_i w_i t_i, [R] (not normalised by the opacity)."""
    return (weights * t).sum(dim=-1)


def over_background(rgb: torch.Tensor, acc: torch.Tensor, background: torch.Tensor) -> torch.Tensor:
    """Composite a premultiplied colour [R, 3] with opacity [R] over a background [3] or [R, 3]."""
    return rgb + (1.0 - acc[..., None]) * background
