"""The edit's 3D gate: where the editing field may change the template (beyond the paper).

The paper keeps the unedited parts in place softly (L_reg). Here the displacements of F_dG and
F'_dG and the modification colour of F_dT are also multiplied by a gate w(x) in [0, 1] that is 1
near the part the shape prior moved and falls smoothly to 0 away from it, so everything the edit
does not touch renders exactly as the template (the hash table of F_dT and the MLPs of the
deformations cannot leak into it). The gate is a voxel grid over [-bound, bound]^3 sampled
trilinearly; without `set_from_points` it is 1 everywhere (no gating).
"""

from __future__ import annotations

import numpy as np
import torch
import torch.nn.functional as F
from scipy import ndimage
from torch import nn


class EditGate(nn.Module):
    """x [N, 3] -> w [N] in [0, 1] (1 everywhere until `set_from_points`)."""

    def __init__(self, bound: float = 1.0):
        super().__init__()
        self.bound = float(bound)
        self.register_buffer("grid", torch.ones(1, 1, 2, 2, 2))  # [1, 1, D, H, W] = z, y, x

    @torch.no_grad()
    def set_from_points(
        self, points: np.ndarray, inner: float, outer: float, resolution: int = 64
    ) -> None:
        """w = 1 within `inner` (run units) of any of `points` [M, 3], 0 beyond `outer`, linear
        in between (the distance measured on a voxel grid of `resolution`^3)."""
        voxel = 2 * self.bound / resolution
        occupied = np.zeros((resolution,) * 3, bool)
        ijk = np.floor((np.asarray(points) + self.bound) / voxel).astype(int)
        ijk = np.clip(ijk, 0, resolution - 1)
        occupied[ijk[:, 2], ijk[:, 1], ijk[:, 0]] = True  # [z, y, x]
        dist = ndimage.distance_transform_edt(~occupied) * voxel if occupied.any() else None
        if dist is None:
            w = np.ones_like(occupied, np.float32)
        else:
            w = np.clip((outer - dist) / max(outer - inner, 1e-6), 0.0, 1.0).astype(np.float32)
        self.grid = torch.from_numpy(w)[None, None].to(self.grid.device)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        g = (x / self.bound).clamp(-1, 1).view(1, -1, 1, 1, 3)  # grid_sample order: x, y, z
        w = F.grid_sample(self.grid, g, mode="bilinear", padding_mode="border", align_corners=False)
        return w.view(-1)

    def _load_from_state_dict(self, state_dict, prefix, *args, **kwargs):
        # the grid's resolution is whatever was saved
        key = prefix + "grid"
        if key in state_dict:
            self.grid = torch.empty_like(state_dict[key])
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)
