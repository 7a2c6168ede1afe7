"""Semantic masks (SINE Sec. 3): which pixels of any view belong to the edited part.

From the DINO feature map of the editing view and the user's painted region: sample features
inside the region, K-means them, and in any view mark a pixel editable when its L2-normalised
feature lies within `threshold` of the nearest (normalised) centre. Everything else is
background, where L_reg keeps the template.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from render.configs import option
from render.errors import SineError


@dataclass
class SemanticMaskConfig:
    """K-means masks from DINO features (the paper's numbers are the defaults)."""

    num_samples: int = option(
        1000, "features sampled (seeded) inside the painted region of the editing view"
    )
    num_clusters: int = option(15, "K-means centres K fitted to the region's features")
    threshold: float = option(
        0.5,
        "a pixel is editable when the distance from its L2-normalised feature to the nearest "
        "centre is below this (unit vectors: 0.5 <=> cosine > 0.875)",
    )
    kmeans_init: int = option(3, "K-means restarts (scikit-learn n_init)")
    seed: int = option(0, "seed of the feature sampling and of K-means")


def _as_chw(features) -> torch.Tensor:
    f = torch.as_tensor(features).detach().float()
    if f.dim() != 3:
        raise ValueError(f"expected a feature map [C, H, W], got {tuple(f.shape)}")
    return f


def _resize_mask(mask, size: tuple[int, int]) -> torch.Tensor:
    """Bool mask [H', W'] -> [H, W] by nearest neighbour (pixel centres)."""
    m = torch.as_tensor(np.asarray(mask)).bool()
    if tuple(m.shape) == tuple(size):
        return m
    return F.interpolate(m[None, None].float(), size=size, mode="nearest-exact")[0, 0] > 0.5


def fit_region_centres(features, region, config: SemanticMaskConfig | None = None) -> torch.Tensor:
    """K-means centres [K, C] (unit length) of features [C, H, W] inside `region` [H, W].

    The region may have another resolution than the feature map (resized, nearest).
    """
    from sklearn.cluster import KMeans

    cfg = config or SemanticMaskConfig()
    f = _as_chw(features)
    mask = _resize_mask(region, tuple(f.shape[1:]))
    inside = F.normalize(f[:, mask.to(f.device)].T, dim=1).cpu().numpy()  # [N, C]
    if len(inside) == 0:
        raise SineError("the painted region is empty: paint the part to edit in the editing view")
    rng = np.random.default_rng(cfg.seed)
    replace = len(inside) < cfg.num_samples
    picks = rng.choice(len(inside), size=cfg.num_samples, replace=replace)
    samples = inside[picks].astype(np.float64)
    k = min(cfg.num_clusters, len(np.unique(samples.round(6), axis=0)))
    km = KMeans(n_clusters=k, n_init=cfg.kmeans_init, random_state=cfg.seed).fit(samples)
    centres = torch.from_numpy(km.cluster_centers_).float()
    return F.normalize(centres, dim=1).to(f.device)  # [K, C]


def nearest_centre_distance(features, centres: torch.Tensor, chunk: int = 65536) -> torch.Tensor:
    """Distance [H, W] from each L2-normalised feature of [C, H, W] to its nearest centre."""
    f = _as_chw(features)
    c, h, w = f.shape
    flat = F.normalize(f.reshape(c, -1).T, dim=1)  # [H*W, C]
    centres = centres.to(flat)
    out = torch.cat([torch.cdist(x, centres).min(dim=1).values for x in flat.split(chunk)])
    return out.reshape(h, w)


class SemanticMasks:
    """Fitted once on the editing view; `mask(features)` gives any view's editable pixels."""

    def __init__(self, features, region, config: SemanticMaskConfig | None = None):
        self.config = config or SemanticMaskConfig()
        self.centres = fit_region_centres(features, region, self.config)  # [K, C]

    def distance(self, features) -> torch.Tensor:
        """[H, W] distance to the nearest centre."""
        return nearest_centre_distance(features, self.centres)

    def mask(self, features) -> torch.Tensor:
        """Bool [H, W]: True where editable (distance < threshold)."""
        return self.distance(features) < self.config.threshold
