"""Geometric modification fields of the editing field (paper Sec. 3.1 + supplementary).

`DeformationField` is F_dG (edited space -> template space, x' = x + MLP(PE(x))) and, with the same
shape, the forward field F'_dG (template space -> edited space) that warps the proxy mesh: an MLP of
one hidden layer of 128 (ReLU) on the positional encoding of the input (4 frequencies), whose output
layer starts near zero (uniform in [-1e-4, 1e-4], as the official release) so editing starts at the
identity.

Edit strength: `strength` t in [0, 1] scales the learned displacement (x' = x + t * MLP(PE(x))), so
t = 0 is the template and t = 1 the full edit; intermediate values give a linear blend of
displacements for animated transitions. (The paper's supplementary instead feeds t as an extra
learned input; scaling needs no training on intermediate edits and is exact at both ends.)
"""

from __future__ import annotations

import torch
from torch import nn


class PositionalEncoding(nn.Module):
    """NeRF's encoding: x [N, D] -> [x, sin(2^k pi x), cos(2^k pi x) for k < n_freqs] [N, D(1+2F)]."""

    def __init__(self, n_freqs: int = 4, include_input: bool = True):
        super().__init__()
        self.n_freqs = n_freqs
        self.include_input = include_input
        self.register_buffer("freqs", (2.0 ** torch.arange(n_freqs)) * torch.pi, persistent=False)

    def output_dim(self, input_dim: int) -> int:
        return input_dim * (2 * self.n_freqs + (1 if self.include_input else 0))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        scaled = x[..., None, :] * self.freqs[:, None]  # [N, F, D]
        enc = torch.cat([torch.sin(scaled), torch.cos(scaled)], dim=-2).flatten(-2)  # [N, 2FD]
        return torch.cat([x, enc], dim=-1) if self.include_input else enc


class DeformationField(nn.Module):
    """x [N, 3] -> x + strength * MLP(PE(x)) [N, 3] (F_dG, or F'_dG for the forward direction)."""

    def __init__(self, n_freqs: int = 4, hidden: int = 128, init_range: float = 1e-4, gate=None):
        super().__init__()
        # optional module x [N, 3] -> [N] scaling the displacement; not a submodule (its owner,
        # e.g. EditingField, saves it once)
        object.__setattr__(self, "gate", gate)
        self.encoding = PositionalEncoding(n_freqs)
        self.mlp = nn.Sequential(
            nn.Linear(self.encoding.output_dim(3), hidden), nn.ReLU(), nn.Linear(hidden, 3)
        )
        nn.init.uniform_(self.mlp[-1].weight, -init_range, init_range)
        nn.init.uniform_(self.mlp[-1].bias, -init_range, init_range)

    def displacement(self, x: torch.Tensor) -> torch.Tensor:
        """The learned offset MLP(PE(x)) (times the gate, when there is one), [N, 3]."""
        disp = self.mlp(self.encoding(x))
        return disp if self.gate is None else disp * self.gate(x)[:, None]

    def forward(self, x: torch.Tensor, strength: float = 1.0) -> torch.Tensor:
        return x + strength * self.displacement(x)

    def jacobian_norm(self, x: torch.Tensor) -> torch.Tensor:
        """Frobenius norm of d displacement / dx at x [N, 3] -> [N] (differentiable, for L_gr)."""
        x = x.detach().requires_grad_(True)
        disp = self.displacement(x)  # [N, 3]
        rows = [
            torch.autograd.grad(disp[:, k].sum(), x, create_graph=True)[0] for k in range(3)
        ]  # 3 x [N, 3]
        jac = torch.stack(rows, dim=1)  # [N, 3, 3]
        return torch.sqrt((jac**2).sum(dim=(1, 2)) + 1e-12)
