"""The DINO feature field (paper Sec. 3 / DESIGN.md section 7): a 3D point -> a feature vector.

`FeatureField`: its own small hash grid (optionally concatenated with the frozen template's
geometry feature) -> an MLP -> D channels, the coefficients of the DINO patch features in a PCA
basis (mean [C] + components [D, C], stored as buffers) fitted on the captures' foreground
features. Rendered with the frozen template's density weights (same sampler) and composited with
`render.volume.composite`; a pixel's feature is the composite divided by the opacity, decoded
back to the C = 384 DINO channels (`decode`), so the semantic masks work in DINO's own space.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from render.hashgrid import HashGrid, HashGridConfig
from render.renderer import FieldQuery, render_image
from render.template_field import mlp


@dataclass
class FeatureFieldConfig:
    """Architecture of the feature field."""

    grid: HashGridConfig = field(
        default_factory=lambda: HashGridConfig(
            n_levels=12, n_features=2, log2_table=15, base_resolution=16, max_resolution=256
        )
    )
    bound: float = 1.0  # the grid covers [-bound, bound]^3
    out_dim: int = 64  # channels predicted (PCA coefficients)
    feature_dim: int = 384  # channels of the decoded (DINO) features
    hidden: int = 64  # hidden width of the MLP
    hidden_layers: int = 2  # hidden layers of the MLP
    geo_feat_dim: int = 0  # > 0: the template's geometry feature is an extra input


class FeatureField(nn.Module):
    """x [N, 3] (+ geo_feat [N, G]) -> PCA coefficients [N, D]; `decode` -> DINO features [.., C]."""

    def __init__(self, cfg: FeatureFieldConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or FeatureFieldConfig()
        self.grid = HashGrid(cfg.grid, bound=cfg.bound)
        self.net = mlp(
            self.grid.output_dim + cfg.geo_feat_dim, cfg.hidden, cfg.hidden_layers, cfg.out_dim
        )
        self.register_buffer("mean", torch.zeros(cfg.feature_dim))  # [C]
        eye = torch.eye(cfg.out_dim, cfg.feature_dim)
        self.register_buffer("components", eye)  # [D, C], orthonormal rows

    def set_basis(self, mean: torch.Tensor, components: torch.Tensor) -> None:
        """The PCA basis: mean [C], components [D, C] (features ~ mean + coeffs @ components)."""
        self.mean.copy_(mean.to(self.mean))
        self.components.copy_(components.to(self.components))

    def project(self, features: torch.Tensor) -> torch.Tensor:
        """DINO features [..., C] -> PCA coefficients [..., D]."""
        return (features - self.mean) @ self.components.T

    def decode(self, coeffs: torch.Tensor) -> torch.Tensor:
        """PCA coefficients [..., D] -> DINO features [..., C]."""
        return coeffs @ self.components + self.mean

    def forward(self, x: torch.Tensor, geo_feat: torch.Tensor | None = None) -> torch.Tensor:
        h = self.grid(x)  # [N, L*F]
        if self.cfg.geo_feat_dim:
            h = torch.cat([h, geo_feat.to(h)], dim=-1)
        return self.net(h)  # [N, D]

    def param_groups(self, lr_grid: float, lr_mlp: float, weight_decay_mlp: float = 1e-6):
        """Adam groups: the hash table (tiny eps, no weight decay) and the MLP."""
        return [
            {"params": [self.grid.table], "lr": lr_grid, "eps": 1e-15, "name": "grid"},
            {
                "params": list(self.net.parameters()),
                "lr": lr_mlp,
                "weight_decay": weight_decay_mlp,
                "name": "mlp",
            },
        ]


def feature_query(template: nn.Module, features: FeatureField) -> FieldQuery:
    """A FieldQuery for `render.renderer`: the frozen template's density + a "feat" channel."""

    def query(points: torch.Tensor, dirs: torch.Tensor) -> dict[str, torch.Tensor]:
        with torch.no_grad():
            sigma, geo = template.geometry(points)  # [M], [M, G]
        return {"sigma": sigma, "feat": features(points, geo)}

    return query


def render_feature_map(
    camera,
    template: nn.Module,
    features: FeatureField,
    sampler,
    chunk: int = 16384,
    device: torch.device | None = None,
    decode: bool = True,
    min_opacity: float = 1e-3,
) -> dict[str, np.ndarray]:
    """One camera -> {"features" [H, W, C] (decoded, or [H, W, D] coefficients without decode),
    "opacity" [H, W]}: the composited feature divided by the opacity (0 where the opacity is below
    `min_opacity`)."""
    out = render_image(camera, feature_query(template, features), sampler, None, chunk, device)
    acc = out["opacity"]  # [H, W]
    coeffs = out["feat"] / np.maximum(acc, min_opacity)[..., None]  # [H, W, D]
    fg = acc >= min_opacity
    if decode:
        with torch.no_grad():
            dec = features.decode(torch.from_numpy(coeffs).to(features.mean.device))
        coeffs = dec.cpu().numpy()
    coeffs = np.where(fg[..., None], coeffs, 0.0).astype(np.float32)
    return {"features": coeffs, "opacity": acc}


def pca_rgb(
    coeffs: np.ndarray, mask: np.ndarray | None = None, lo=None, hi=None, background: float = 1.0
) -> np.ndarray:
    """The first three PCA coefficients [H, W, >=3] as RGB [H, W, 3] in [0, 1].

    `lo`/`hi` ([3]) fix the colour range (e.g. from the training features' percentiles) so that
    several images share one mapping; `mask` [H, W] paints the rest with `background`.
    """
    rgb = np.asarray(coeffs, np.float32)[..., :3]
    if lo is None or hi is None:
        sel = rgb[mask] if mask is not None and mask.any() else rgb.reshape(-1, 3)
        lo, hi = np.percentile(sel, 1, axis=0), np.percentile(sel, 99, axis=0)
    rgb = np.clip((rgb - np.asarray(lo)) / np.maximum(np.asarray(hi) - np.asarray(lo), 1e-6), 0, 1)
    if mask is not None:
        rgb = np.where(mask[..., None], rgb, background)
    return rgb.astype(np.float32)
