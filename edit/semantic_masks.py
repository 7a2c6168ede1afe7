"""Semantic masks (SINE Sec. 3): which pixels of any view belong to the edited part.

From the DINO feature map of the editing view and the user's painted region: sample features
inside the region and K-means them ("part" centres). Two rules mark a pixel of any view editable:

- `threshold` (the paper's): its L2-normalised feature lies within `threshold` of the nearest
  part centre;
- `contrast` (default): the same K-means on the rest of the object in the editing view gives
  "other" centres, and a pixel is editable when its feature is nearer to a part centre than to
  any other centre. No absolute distance to tune: a face of the part that looks a little different
  from the painted one still goes with the part, while a neighbouring part that looks a little
  like it goes with itself. Without an object mask (or nothing outside the region) it falls back
  to `threshold`.

With the contrast rule, a pixel's 3D surface point goes beside its feature (`spatial`, beyond the
paper): the descriptor is [unit feature, spatial * (x - c) / r], c and r the centre and mean
radius of the object's surface in the editing view. A part lies in one place: surface on another
side of the object that looks like the painted part (white fur above and below a painted line)
but lies among the rest of the object goes with the rest, while the part's own far side, next to
the painted surface, still goes with the part.

With the view's image at hand, the decision is refined: DINO features are blurred over a patch
(~1/16 of the object), so the soft score (distance margin) is guided-filtered with the image,
which moves the mask's edges onto the image's colour edges.

Everything else is background, where L_reg keeps the template.
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
    rule: str = option(
        "contrast",
        "which pixels are editable: 'contrast' = nearer to the painted part's centres than to the "
        "centres of the rest of the object in the editing view; 'threshold' = the paper's rule, "
        "distance to the nearest part centre below --threshold",
        choices=["contrast", "threshold"],
    )
    threshold: float = option(
        0.5,
        "threshold rule: a pixel is editable when the distance from its L2-normalised feature to "
        "the nearest centre is below this (unit vectors: 0.5 <=> cosine > 0.875)",
    )
    rest_margin: int = option(
        4,
        "contrast rule: object pixels within this many pixels of the painted region are not "
        "used as 'rest of the object' (a stroke rarely reaches the part's edge exactly)",
    )
    refine: bool = option(
        True, "snap the masks' edges to the image's colour edges (guided filter on the score)"
    )
    refine_radius: float = option(
        0.06,
        "guided-filter radius as a fraction of the object's size in the view (the DINO crop "
        "spans the object with 16 patches: 0.06 is about one patch)",
    )
    refine_eps: float = option(
        0.01, "guided-filter regularisation (image in [0, 1]): larger follows the image less"
    )
    spatial: float = option(
        0.25,
        "contrast rule: weight of the pixel's 3D surface point beside its DINO feature (distance "
        "in object radii times this, against unit-feature distances): surface that looks like "
        "the painted part but lies among the rest of the object goes with the rest; 0: features "
        "only (the paper)",
        low=0.0,
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


def _unit(x: torch.Tensor, unit_channels: int | None) -> torch.Tensor:
    """Rows [N, D] with the first `unit_channels` columns (None: all) scaled to unit length."""
    if unit_channels is None:
        return F.normalize(x, dim=1)
    return torch.cat([F.normalize(x[:, :unit_channels], dim=1), x[:, unit_channels:]], dim=1)


def fit_region_centres(
    features, region, config: SemanticMaskConfig | None = None, unit_channels: int | None = None
) -> torch.Tensor:
    """K-means centres [K, C] of features [C, H, W] inside `region` [H, W].

    The features (and the centres) are L2-normalised: all channels, or the first
    `unit_channels` (the rest, e.g. positions, are taken as they are). The region may have
    another resolution than the feature map (resized, nearest).
    """
    from sklearn.cluster import KMeans

    cfg = config or SemanticMaskConfig()
    f = _as_chw(features)
    mask = _resize_mask(region, tuple(f.shape[1:]))
    inside = _unit(f[:, mask.to(f.device)].T, unit_channels).cpu().numpy()  # [N, C]
    if len(inside) == 0:
        raise SineError("the painted region is empty: paint the part to edit in the editing view")
    rng = np.random.default_rng(cfg.seed)
    replace = len(inside) < cfg.num_samples
    picks = rng.choice(len(inside), size=cfg.num_samples, replace=replace)
    samples = inside[picks].astype(np.float64)
    k = min(cfg.num_clusters, len(np.unique(samples.round(6), axis=0)))
    km = KMeans(n_clusters=k, n_init=cfg.kmeans_init, random_state=cfg.seed).fit(samples)
    centres = torch.from_numpy(km.cluster_centers_).float()
    return _unit(centres, unit_channels).to(f.device)  # [K, C]


def nearest_centre_distance(
    features, centres: torch.Tensor, chunk: int = 65536, unit_channels: int | None = None
) -> torch.Tensor:
    """Distance [H, W] from each feature of [C, H, W] (L2-normalised as in `fit_region_centres`)
    to its nearest centre."""
    f = _as_chw(features)
    c, h, w = f.shape
    flat = _unit(f.reshape(c, -1).T, unit_channels)  # [H*W, C]
    centres = centres.to(flat)
    out = torch.cat([torch.cdist(x, centres).min(dim=1).values for x in flat.split(chunk)])
    return out.reshape(h, w)


class SemanticMasks:
    """Fitted once on the editing view; `mask(features)` gives any view's editable pixels.

    features [C, H, W] of the editing view, region [H, W] the painted pixels, object_mask [H, W]
    the object's pixels in that view (needed by the contrast rule: the rest of the object is
    object_mask minus the region grown by `rest_margin`), points [H, W, 3] the surface point of
    each pixel (the contrast rule's `spatial` term; every view's `mask` then needs its points).
    """

    def __init__(
        self,
        features,
        region,
        config: SemanticMaskConfig | None = None,
        object_mask=None,
        points=None,
    ):
        self.config = cfg = config or SemanticMaskConfig()
        if cfg.rule not in ("contrast", "threshold"):
            raise SineError(f"unknown mask rule {cfg.rule!r}: contrast or threshold")
        rest = None
        if cfg.rule == "contrast" and object_mask is not None:
            rest = rest_of_object(region, object_mask, cfg.rest_margin)
            if rest.sum() < cfg.num_clusters:
                rest = None
        self.feature_dim = _as_chw(features).shape[0]
        self.frame = None  # (centre [3], radius) of the object's surface: the spatial term's
        if rest is not None and cfg.spatial > 0 and points is not None:
            on = torch.as_tensor(np.asarray(object_mask, bool))
            surface = torch.as_tensor(np.asarray(points, np.float32))[on]  # [N, 3]
            centre = surface.mean(dim=0)
            radius = float((surface - centre).norm(dim=1).mean().clamp_min(1e-6))
            self.frame = (centre, radius)
        described = self.descriptors(features, points)
        unit = self.feature_dim
        self.centres = fit_region_centres(described, region, cfg, unit)  # [K, C (+3)]
        self.other_centres = None  # [K', C (+3)] (contrast rule)
        if rest is not None:
            self.other_centres = fit_region_centres(described, rest, cfg, unit)

    @property
    def rule(self) -> str:
        """The rule in use ('contrast' falls back to 'threshold' without a rest of the object)."""
        return "contrast" if self.other_centres is not None else "threshold"

    def split(self, centres: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Centres [K, C (+3)] -> (feature parts [K, C], surface points [K, 3] in run units, or
        None without the spatial term)."""
        feats = centres[:, : self.feature_dim]
        if self.frame is None:
            return feats, None
        centre, radius = self.frame
        scaled = centres[:, self.feature_dim :]  # (x - c) * spatial / r
        return feats, scaled * (radius / self.config.spatial) + centre.to(centres)

    def descriptors(self, features, points=None) -> torch.Tensor:
        """[C (+3), H, W]: the features (normalised where distances are taken, over the first
        `feature_dim` channels), and with the spatial term the surface points [H, W, 3] in the
        editing view's object frame times `spatial`."""
        f = _as_chw(features)
        if self.frame is None:
            return f
        if points is None:
            raise ValueError("these masks weigh the surface point: give each view's points")
        centre, radius = self.frame
        x = torch.as_tensor(np.asarray(points, np.float32)).to(f)  # [H, W, 3]
        x = (x - centre.to(f)) * (self.config.spatial / radius)
        return torch.cat([f, x.permute(2, 0, 1)], dim=0)

    def score(self, features, points=None) -> torch.Tensor:
        """[H, W] soft decision, > 0 where editable: the distance margin to the rest's centres
        (contrast rule) or to the threshold."""
        described = self.descriptors(features, points)
        unit = self.feature_dim
        d_part = nearest_centre_distance(described, self.centres, unit_channels=unit)
        if self.other_centres is None:
            return self.config.threshold - d_part
        return nearest_centre_distance(described, self.other_centres, unit_channels=unit) - d_part

    def mask(self, features, image=None, object_mask=None, points=None) -> torch.Tensor:
        """Bool [H, W]: True where editable. With the view's image [H, W, 3] (in [0, 1]) and its
        object mask [H, W] (which sets the filter radius), the edges follow the image's; points
        [H, W, 3]: the view's surface points (needed when the masks weigh them)."""
        score = self.score(features, points)
        if image is not None and object_mask is not None and self.config.refine:
            score = guided_refine(
                score, image, object_mask, self.config.refine_radius, self.config.refine_eps
            )
        return score > 0


def guided_refine(score, image, object_mask, radius: float, eps: float) -> torch.Tensor:
    """score [H, W] guided-filtered by image [H, W, 3] (radius: a fraction of the object's longer
    bounding-box side in object_mask [H, W]); an empty object leaves the score as it is."""
    import cv2

    ys, xs = np.nonzero(np.asarray(object_mask))
    score = torch.as_tensor(score)
    if len(xs) == 0:
        return score
    size = max(xs.max() - xs.min(), ys.max() - ys.min()) + 1
    r = max(1, round(radius * size))
    guide = np.ascontiguousarray(np.asarray(image, np.float32)[..., :3])
    src = score.detach().cpu().numpy().astype(np.float32)
    out = cv2.ximgproc.guidedFilter(guide, src, r, eps)
    return torch.from_numpy(out).to(score.device)


def rest_of_object(region, object_mask, margin: int) -> np.ndarray:
    """Object pixels [H, W] farther than `margin` pixels from the painted region."""
    import cv2

    region = np.asarray(region, bool)
    grown = region
    if margin > 0:
        kernel = np.ones((2 * margin + 1, 2 * margin + 1), np.uint8)
        grown = cv2.dilate(region.astype(np.uint8), kernel) > 0
    return np.asarray(object_mask, bool) & ~grown
