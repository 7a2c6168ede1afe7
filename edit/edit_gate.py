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
        self,
        points: np.ndarray,
        inner: float,
        outer: float,
        resolution: int = 64,
        others: np.ndarray | None = None,
    ) -> None:
        """w = 1 within `inner` (run units) of any of `points` [M, 3], 0 beyond `outer`, linear
        in between (the distance measured on a voxel grid of `resolution`^3). `others` [K, 3]:
        surface points that are not the part's. A voxel then is the part's where it holds more
        of `points` than of `others`, and w also falls to 0 within a voxel where the nearest
        voxel of `others` is nearer than the part's: the part's own points outvote the few
        that one view's mask wrongly calls the part, and the gate stops at the neighbours'
        surface instead of spreading `outer` over it. A voxel the part's voxels enclose (a
        binary closing, 3 x 3 x 3 at 128 voxels a side, its reach the same in run units on a
        finer grid) is the part's too: where a few views' masks miss a spot of the part's own
        surface, its voxels lose the vote, and the stop would punch a hole there (the
        template's colour as a dot in the edit)."""
        voxel = 2 * self.bound / resolution
        shape = (resolution,) * 3

        def counts(pts: np.ndarray) -> dict[int, int]:  # flat [z, y, x] voxel -> points in it
            ijk = np.floor((np.asarray(pts).reshape(-1, 3) + self.bound) / voxel).astype(int)
            ijk = np.clip(ijk, 0, resolution - 1)
            keys, n = np.unique(
                np.ravel_multi_index((ijk[:, 2], ijk[:, 1], ijk[:, 0]), shape), return_counts=True
            )
            return dict(zip(keys.tolist(), n.tolist(), strict=True))

        inside = counts(points)
        outside = counts(others) if others is not None else {}
        voted = np.array([k for k, n in inside.items() if n > outside.get(k, 0)], np.int64)
        if len(voted) == 0:  # no part: no gating
            self.grid = torch.ones(1, 1, *shape, device=self.grid.device)
            return
        # Everything below happens in a box around the part: w is 0 farther than `outer` from it,
        # and a neighbour farther than 2 `outer` (+ 2 voxels) cannot stop it (the result is the
        # whole grid's; a finer grid costs the part's box, not the whole cube).
        zyx = np.stack(np.unravel_index(voted, shape), axis=1)  # [V, 3]
        margin = int(np.ceil(2 * outer / voxel)) + 2
        lo = np.maximum(zyx.min(axis=0) - margin, 0)
        hi = np.minimum(zyx.max(axis=0) + margin + 1, resolution)
        box = tuple(slice(a, b) for a, b in zip(lo, hi, strict=True))

        def in_box(keys) -> np.ndarray:  # [z, y, x] bool of the box: the voxels `keys`
            grid = np.zeros(tuple(hi - lo), bool)
            zyx = np.stack(np.unravel_index(np.asarray(keys, np.int64), shape), axis=1) - lo
            zyx = zyx[np.all((zyx >= 0) & (zyx < hi - lo), axis=1)]  # [K, 3] in the box
            grid[tuple(zyx.T)] = True
            return grid

        occupied = in_box(voted)
        if others is not None:  # the part's holes are the part's
            reach = max(1, round(resolution / 128))  # the closing's size in run units, as at 128
            occupied |= ndimage.binary_closing(occupied, np.ones((3, 3, 3), bool), iterations=reach)
        dist = ndimage.distance_transform_edt(~occupied) * voxel
        w = np.clip((outer - dist) / max(outer - inner, 1e-6), 0.0, 1.0)
        other = in_box(list(outside)) & ~occupied
        if other.any():  # nearer the neighbours' surface than the part's: 0
            to_other = ndimage.distance_transform_edt(~other) * voxel
            w *= np.clip((to_other - dist) / voxel + 0.5, 0.0, 1.0)
        grid = np.zeros(shape, np.float32)
        grid[box] = w
        self.grid = torch.from_numpy(grid)[None, None].to(self.grid.device)

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
