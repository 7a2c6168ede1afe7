"""The colour-detail phase of `sine fit`: the fine texture the main fit leaves soft.

Why. The main fit trains density and colour together, 21 field samples per ray, 10-20k rays/s
on 2 cores: in its 1500 steps each training pixel is drawn about four times. On a real capture
the fine texture stays soft (the oxford-dinosaur's held-out views 24.7-25.1 dB where both ring
neighbours' photos, warped into them through the template's own depth, score 29-30 dB:
bench/HISTORY.md "The colour-detail phase", `bench/bench_view_consistency.py`).

How. When the main fit has finished (its moving average in place) the density is frozen, so
every training ray's sample weights are fixed. They are computed once (`build_detail_cache`):
each ray keeps the samples whose weight exceeds `MIN_WEIGHT` (2-6 of 21 on the benchmarks) and
the colour head's logits there. Then only the field's detail branch (`TemplateField.detail_grid`
/ `detail_net`, render/template_field.py; left out of the main steps) learns an offset to the
colour logits, on the cached samples of many rays per step (`detail_step`: 5-12x the rays per
second of a main step). Density, the geometry feature and the main colour head stay as the main
fit left them, so the geometry the edits and the feature field build on does not move.

The check (`--detail-check`, `check_views` / `check_psnr`). On a sparse ring whose template
fails (dinoSparseRing: 14 views, the head a blotchy mass) the branch memorises the few views and
paints view-dependent speckle onto the wrong surface (held-out -0.6 dB). So the phase's first
steps leave every CHECK_EVERY-th training view out; the branch is kept only if it then renders
those views' cached rays better than the field without it (dinoSparseRing 27.6 -> 25.2 dB after
300 steps: dropped, zeroed by `reset_branch`; the oxford-dinosaur 25.6 -> 25.9: kept), and then
trains on all the rays (leaving the views out for good costs the dinosaur 0.4 dB).

When the main fit box-filters (`--train-supersample` > 1) the masks' edge pixels are left out:
such a pixel is part object, part background, and one cached centre ray cannot match its mean.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from render import volume
from render.renderer import sample_hits
from render.sh import sh_encode
from render.template_field import TemplateField

MIN_WEIGHT = 1e-3  # samples below this rendering weight are left out of the cache
MAX_CACHED_RAYS = 2_000_000  # beyond this many training rays, a random subset is cached
CHECK_EVERY = 6  # the check holds out every 6th training view...
CHECK_MIN_VIEWS = 6  # ...when there are at least this many


@dataclass
class DetailCache:
    """The frozen field's samples of the training rays, ray by ray (a ray's samples are
    contiguous: `start`, `count`)."""

    points: torch.Tensor  # [S, 3] kept samples
    weights: torch.Tensor  # [S] their rendering weights
    base_logits: torch.Tensor  # [S, 3] the colour head's logits without the detail branch
    start: torch.Tensor  # [R] int64: each ray's first sample
    count: torch.Tensor  # [R] int64: each ray's kept samples
    dirs: torch.Tensor  # [R, 3] unit ray directions
    target: torch.Tensor  # [R, 3] the pixel's colour
    behind: torch.Tensor  # [R, 3] what the ray composites over (background or captured pixel)
    opacity: torch.Tensor  # [R] the ray's opacity over all its samples

    def __len__(self) -> int:
        return len(self.start)


def detail_rays(pool, box_filtered_edges: bool, generator: torch.Generator) -> torch.Tensor:
    """Indices into `pool` of the rays the detail phase trains on [R]: all of them but the
    masks' edge pixels when the main fit box-filters those, at most MAX_CACHED_RAYS (a random
    subset, sorted)."""
    rays = torch.arange(len(pool.origins), device=pool.origins.device)
    if box_filtered_edges:
        rays = rays[~pool.edge]
    if len(rays) > MAX_CACHED_RAYS:
        pick = torch.randperm(len(rays), generator=generator)[:MAX_CACHED_RAYS]
        rays = rays[pick.to(rays.device).sort().values]
    return rays


@torch.no_grad()
def build_detail_cache(
    field: TemplateField,
    sampler,
    pool,
    rays: torch.Tensor,
    behind: torch.Tensor,
    chunk: int = 16384,
) -> DetailCache:
    """Samples, weights and colour logits of the frozen `field` along the pool's `rays` [R]
    (indices into `pool`; `behind` [R, 3] what each composites over)."""
    points, weights, logits, counts, opacity = [], [], [], [], []
    for first in range(0, len(rays), chunk):
        idx = rays[first : first + chunk]
        o, d = pool.origins[idx], pool.dirs[idx]  # [r, 3]
        hits = pool.hits[idx]
        t, delta, _ = sample_hits(sampler, hits, o, d, lambda x, v: field.density(x))  # [r, S]
        x = o[:, None, :] + d[:, None, :] * t[..., None]  # [r, S, 3]
        sigma, geo = field.geometry(x.reshape(-1, 3))
        w = volume.render_weights(sigma.view(t.shape), t, delta=delta)  # [r, S]
        ray, sample = torch.nonzero(w > MIN_WEIGHT, as_tuple=True)  # ray-major order
        kept_geo = geo.view(*t.shape, -1)[ray, sample]  # [k, F]
        points.append(x[ray, sample])
        weights.append(w[ray, sample])
        logits.append(field.color_logits(kept_geo, d[ray], detail=False))
        counts.append(torch.bincount(ray, minlength=len(idx)))
        opacity.append(volume.opacity(w))
    count = torch.cat(counts)
    return DetailCache(
        points=torch.cat(points),
        weights=torch.cat(weights),
        base_logits=torch.cat(logits),
        start=torch.cumsum(count, 0) - count,
        count=count,
        dirs=pool.dirs[rays],
        target=pool.rgb[rays],
        behind=behind,
        opacity=torch.cat(opacity),
    )


def composite(
    field: TemplateField, cache: DetailCache, rays: torch.Tensor, detail: bool = True
) -> torch.Tensor:
    """The colour [B, 3] of cached rays `rays` [B] (indices into the cache) composited from
    their cached weights and colour logits, plus the detail branch's offset when `detail`."""
    device = cache.points.device
    count = cache.count[rays]  # [B]
    owner = torch.repeat_interleave(torch.arange(len(rays), device=device), count)  # [k]
    first_of_owner = torch.repeat_interleave(torch.cumsum(count, 0) - count, count)
    sample = cache.start[rays][owner] + torch.arange(len(owner), device=device) - first_of_owner
    logits = cache.base_logits[sample]  # [k, 3]
    if detail:
        sh = sh_encode(cache.dirs[rays][owner], field.cfg.sh_degree)  # [k, K]
        logits = logits + field.detail_logits(cache.points[sample], sh)
    rgb = torch.sigmoid(logits)
    colour = torch.zeros(len(rays), 3, device=device, dtype=rgb.dtype)
    colour = colour.index_add(0, owner, cache.weights[sample, None] * rgb)
    return colour + (1.0 - cache.opacity[rays, None]) * cache.behind[rays]


def detail_step(
    field: TemplateField,
    cache: DetailCache,
    batch_rays: int,
    generator: torch.Generator,
    among: torch.Tensor | None = None,
) -> dict[str, torch.Tensor]:
    """One step's loss of the detail branch: `batch_rays` cached rays drawn uniformly (from
    the cache indices `among` [M] when given), composited with the branch's offset."""
    device = cache.points.device
    pool_size = len(cache) if among is None else len(among)
    rays = torch.randint(pool_size, (batch_rays,), generator=generator).to(device)  # [B]
    if among is not None:
        rays = among[rays]
    pred = composite(field, cache, rays)
    return {"rgb": ((pred - cache.target[rays]) ** 2).mean()}


def check_views(view_of_ray: torch.Tensor, n_views: int) -> torch.Tensor:
    """Which cached rays [R] bool belong to the views the check holds out: every
    CHECK_EVERY-th training view (from the middle of the first group); none with fewer than
    CHECK_MIN_VIEWS views. `view_of_ray` [R]: each cached ray's training view."""
    held = torch.zeros(n_views, dtype=torch.bool, device=view_of_ray.device)
    if n_views >= CHECK_MIN_VIEWS:
        held[CHECK_EVERY // 2 :: CHECK_EVERY] = True
    return held[view_of_ray]


@torch.no_grad()
def check_psnr(
    field: TemplateField, cache: DetailCache, rays: torch.Tensor, chunk: int = 65536
) -> tuple[float, float]:
    """PSNR (dB) of the cached rays `rays` [M] without and with the detail branch."""
    sums = [0.0, 0.0]
    for first in range(0, len(rays), chunk):
        part = rays[first : first + chunk]
        for k, detail in enumerate((False, True)):
            error = (composite(field, cache, part, detail) - cache.target[part]) ** 2
            sums[k] += float(error.mean(dim=1).sum())
    return tuple(-10.0 * math.log10(max(s / max(len(rays), 1), 1e-12)) for s in sums)


def reset_branch(field: TemplateField) -> None:
    """Zeroes the branch's last layer: the field renders exactly as without the branch."""
    with torch.no_grad():
        field.detail_net[-1].weight.zero_()
        field.detail_net[-1].bias.zero_()
