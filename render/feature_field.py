"""The DINO feature field (paper Sec. 3 / DESIGN.md section 7): a 3D point -> a feature vector.

`FeatureField`: its own small hash grid -> an MLP -> D channels, the coefficients of the DINO patch features in a PCA
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

from render import volume
from render.hashgrid import HashGrid, HashGridConfig
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
    top_k: int = 8  # samples composited per ray (largest template weights), training = rendering


class FeatureField(nn.Module):
    """x [N, 3] -> PCA coefficients [N, D]; `decode` -> DINO features [.., C]."""

    def __init__(self, cfg: FeatureFieldConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or FeatureFieldConfig()
        self.grid = HashGrid(cfg.grid, bound=cfg.bound)
        self.net = mlp(self.grid.output_dim, cfg.hidden, cfg.hidden_layers, cfg.out_dim)
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

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.net(self.grid(x))  # [N, D]

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


def fit_pca(
    x: torch.Tensor, dim: int, max_samples: int = 100_000, seed: int = 0
) -> tuple[torch.Tensor, torch.Tensor]:
    """PCA of feature rows x [M, C] (in float64; at most `max_samples` random rows, seeded):
    mean [C] and the `dim` leading components [dim, C] (orthonormal rows), float32: the basis
    of `FeatureField.set_basis`."""
    x = x.double()
    if len(x) > max_samples:
        g = torch.Generator().manual_seed(seed)
        x = x[torch.randperm(len(x), generator=g)[:max_samples]]
    mean = x.mean(0)
    _, _, v = torch.linalg.svd(x - mean, full_matrices=False)  # [C, C]
    return mean.float(), v[:dim].float()


@dataclass
class TopKSamples:
    """Per ray, the k samples with the largest frozen-template weights."""

    ray: torch.Tensor  # [r] index of the ray among those cast
    points: torch.Tensor  # [r, k, 3]
    weights: torch.Tensor  # [r, k]
    opacity: torch.Tensor  # [r] sum of all the ray's weights


@torch.no_grad()
def top_k_samples(
    template: nn.Module,
    sampler,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    k: int,
    chunk: int = 4096,
) -> TopKSamples:
    """Rays [R, 3] -> top-k samples of the rays that need the field (the sampler's hits)."""
    hits = sampler.cast(origins, dirs)
    idx = torch.nonzero(hits.hit)[:, 0]  # [r]
    parts = []
    for s in range(0, len(idx), chunk):
        sel = idx[s : s + chunk]
        t, delta = sampler.sample(hits[sel], False)  # [c, S]
        p = origins[sel, None, :] + dirs[sel, None, :] * t[..., None]  # [c, S, 3]
        sigma, _ = template.geometry(p.reshape(-1, 3))
        w = volume.render_weights(sigma.view(t.shape), t, delta=delta)  # [c, S]
        wk, ik = torch.topk(w, min(k, t.shape[1]), dim=1)  # [c, k]
        pk = torch.gather(p, 1, ik[..., None].expand(-1, -1, 3))
        parts.append((pk, wk, volume.opacity(w)))
    if not parts:
        z = origins.new_zeros
        return TopKSamples(idx, z(0, k, 3), z(0, k), z(0))
    points, weights, opacity = (torch.cat(q) for q in zip(*parts, strict=True))
    return TopKSamples(idx, points, weights, opacity)


def composite_features(
    features: FeatureField, points: torch.Tensor, weights: torch.Tensor
) -> torch.Tensor:
    """Top-k samples (points [r, k, 3], weights [r, k]) -> rendered coefficients [r, D]:
    composite(weights, field(points)) / sum of the weights."""
    f = features(points.reshape(-1, 3)).view(*weights.shape, -1)  # [r, k, D]
    comp = volume.composite(weights, {"feat": f})["feat"]  # [r, D]
    return comp / volume.opacity(weights).clamp_min(1e-3)[:, None]


def render_feature_map(
    camera,
    template: nn.Module,
    features: FeatureField,
    sampler,
    top_k: int | None = None,
    chunk: int = 4096,
    device: torch.device | None = None,
    decode: bool = True,
    min_opacity: float = 1e-3,
    warp=None,
) -> dict[str, np.ndarray]:
    """One camera -> {"features" [H, W, C] (decoded, or [H, W, D] coefficients without decode),
    "opacity" [H, W], "points" [H, W, 3]}: features composited from the top-k samples per ray
    (default: as in training) and divided by their weight (0 where the opacity is below
    `min_opacity`); points likewise, the surface point of each pixel (before any warp).
    `warp`: samples [N, 3] -> the feature field's input points [N, 3] (e.g. a geometric edit's
    map to the template, whose `geometry` the `template` argument then wraps); default: as is."""
    device = device or features.mean.device
    top_k = top_k or features.cfg.top_k
    o, d = (torch.from_numpy(a).to(device) for a in camera.rays())  # [R, 3]
    s = top_k_samples(template, sampler, o, d, top_k, chunk)
    with torch.no_grad():
        coeffs = torch.zeros(len(o), features.cfg.out_dim, device=device)  # [R, D]
        surface = torch.zeros(len(o), 3, device=device)  # [R, 3]
        for a in range(0, len(s.ray), chunk):
            b = slice(a, a + chunk)
            points = s.points[b]  # [c, k, 3]
            kept = volume.opacity(s.weights[b]).clamp_min(1e-3)[:, None]  # [c, 1]
            surface[s.ray[b]] = (s.weights[b, :, None] * points).sum(dim=1) / kept
            if warp is not None:
                points = warp(points.reshape(-1, 3)).view(points.shape)
            coeffs[s.ray[b]] = composite_features(features, points, s.weights[b])
        acc = torch.zeros(len(o), device=device).index_put((s.ray,), s.opacity)  # [R]
        fg = acc >= min_opacity
        out = features.decode(coeffs) if decode else coeffs
        out = torch.where(fg[:, None], out, torch.zeros_like(out))
        surface = torch.where(fg[:, None], surface, torch.zeros_like(surface))
    h, w = camera.height, camera.width
    return {
        "features": out.reshape(h, w, -1).cpu().numpy().astype(np.float32),
        "opacity": acc.reshape(h, w).cpu().numpy(),
        "points": surface.reshape(h, w, 3).cpu().numpy().astype(np.float32),
    }


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
