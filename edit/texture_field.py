"""Texture modification field F_dT (paper Sec. 3.1 + supplementary): a point -> modification colour.

Its own hash grid (same shape as the template's) followed by an MLP of one hidden layer of 128
(ReLU) -> 3 channels, `sigmoid * 2 - 1` (as the official release), so m' lies in (-1, 1). The
output layer starts at zero, so m' = 0 (no modification) before training.

Coarse-to-fine (Nerfies' windowed encoding, the paper's supplementary): the hash levels are
weighted by a cosine window w_l(a) = (1 - cos(pi * clamp(a - l, 0, 1))) / 2 for level l, where
the window position a grows from `window_start` to the number of levels during training;
`set_progress(fraction)` moves it. Level 0 is always fully on.

With `cond_dim` > 0 (beyond the paper) the MLP also reads a per-point condition [N, cond_dim]:
texture edits give it the frozen template's geometry feature at the point (what the template's
own colour head reads), so points that look alike in the template (a stripe, the body around
it) can change differently and the change recurs wherever the template's feature does, on the
part's sides view K does not show too (the hash grid alone knows only positions).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from render.hashgrid import HashGrid, HashGridConfig


def cosine_window(n_levels: int, alpha: float) -> torch.Tensor:
    """Per-level weights [L] of the coarse-to-fine window at position `alpha` (levels 0..L-1)."""
    levels = torch.arange(n_levels, dtype=torch.float32)
    x = (alpha - levels).clamp(0.0, 1.0)
    weights = 0.5 * (1.0 - torch.cos(math.pi * x))
    weights[0] = 1.0
    return weights


class TextureField(nn.Module):
    """x [N, 3] (template space) and optionally a condition [N, C] -> modification colour m'
    [N, 3] in (-1, 1)."""

    def __init__(
        self,
        grid: HashGridConfig | None = None,
        hidden: int = 128,
        bound: float = 1.0,
        window_start: float = 1.0,
        gate=None,
        cond_dim: int = 0,
    ):
        super().__init__()
        # optional module x [N, 3] -> [N] scaling the modification colour; not a submodule (its owner,
        # e.g. EditingField, saves it once)
        object.__setattr__(self, "gate", gate)
        self.grid = HashGrid(grid or HashGridConfig(log2_table=15), bound=bound)
        self.cond_dim = int(cond_dim)
        self.mlp = nn.Sequential(
            nn.Linear(self.grid.output_dim + self.cond_dim, hidden), nn.ReLU(), nn.Linear(hidden, 3)
        )
        nn.init.zeros_(self.mlp[-1].weight)
        nn.init.zeros_(self.mlp[-1].bias)
        self.window_start = float(window_start)
        self.register_buffer("window", torch.ones(self.grid.cfg.n_levels))

    def set_progress(self, fraction: float) -> None:
        """Coarse-to-fine: fraction 0 -> only the first `window_start` levels, 1 -> all levels."""
        n = self.grid.cfg.n_levels
        alpha = self.window_start + (n - self.window_start) * min(max(fraction, 0.0), 1.0)
        self.window.copy_(cosine_window(n, alpha))

    def forward(self, x: torch.Tensor, cond: torch.Tensor | None = None) -> torch.Tensor:
        """x [N, 3], cond [N, cond_dim] (required when cond_dim > 0, else ignored) -> m' [N, 3]."""
        feats = self.grid(x).view(x.shape[0], self.grid.cfg.n_levels, -1)  # [N, L, F]
        feats = (feats * self.window[None, :, None]).flatten(1)
        if self.cond_dim:
            if cond is None:
                raise ValueError("this texture field reads a condition: pass cond [N, cond_dim]")
            feats = torch.cat([feats, cond.to(feats.dtype)], dim=1)
        mod = torch.sigmoid(self.mlp(feats)) * 2.0 - 1.0
        return mod if self.gate is None else mod * self.gate(x)[:, None]
