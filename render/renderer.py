"""Render rays and images through any field with a sampler (proxy band or uniform).

`field_query(points [M, 3], dirs [M, 3]) -> {"sigma": [M], "rgb": [M, 3], ...}`: every returned
channel other than "sigma" (and "geo_feat") is composited with the same weights, so dual
rendering and feature channels come for free. Only rays the sampler marks as hits query the
field; the others get the background (colour) and zero opacity.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import torch

from render import volume
from render.sampler import RayHits

FieldQuery = Callable[[torch.Tensor, torch.Tensor], dict[str, torch.Tensor]]
SKIP_CHANNELS = ("sigma", "geo_feat")


def _background(background, n: int, ref: torch.Tensor) -> torch.Tensor:
    """Background as [n, 3] (from a [3] tensor, a module/callable returning [3], or None)."""
    if background is None:
        bg = torch.zeros(3)
    elif callable(background):
        bg = background()
    else:
        bg = torch.as_tensor(background, dtype=ref.dtype)
    return bg.to(device=ref.device, dtype=ref.dtype).expand(n, 3)


def render_rays(
    field_query: FieldQuery,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    sampler,
    background=None,
    hits: RayHits | None = None,
    perturb: bool = False,
    generator: torch.Generator | None = None,
    keep_weights: bool = False,
) -> dict[str, torch.Tensor]:
    """origins, dirs [R, 3] -> {"rgb" [R, 3] over background, "opacity" [R], "depth" [R],
    other channels [R, C], "hit" [R] bool, "samples" (field queries made)}; with
    `keep_weights`, also the hit rays' samples: "weights", "t", "delta" [r, S].

    "depth" is the expected ray distance normalised by the opacity (0 where nothing is hit).
    Differentiable w.r.t. the field; chunking is the caller's business (see `render_rays_chunked`).
    """
    n_rays = origins.shape[0]
    if hits is None:
        hits = sampler.cast(origins, dirs)
    hit = hits.hit  # [R]
    idx = torch.nonzero(hit)[:, 0]  # [r]
    bg = _background(background, n_rays, origins)  # [R, 3]
    out: dict[str, torch.Tensor] = {
        "rgb": bg,
        "opacity": torch.zeros(n_rays, device=origins.device, dtype=origins.dtype),
        "depth": torch.zeros(n_rays, device=origins.device, dtype=origins.dtype),
        "hit": hit,
        "samples": torch.tensor(0),
    }
    if idx.numel() == 0:
        return out
    sub = hits[idx]
    o, d = origins[idx], dirs[idx]  # [r, 3]
    t, delta = sampler.sample(sub, perturb, generator)  # [r, S]
    if getattr(sampler, "n_importance", 0):
        with torch.no_grad():
            pts = o[:, None, :] + d[:, None, :] * t[..., None]
            sigma = field_query(pts.reshape(-1, 3), d.repeat_interleave(t.shape[1], 0))["sigma"]
            w = volume.render_weights(sigma.view(t.shape), t, delta=delta)
        n_coarse = t.numel()
        t, delta = sampler.importance(sub, t, w, perturb, generator)
    else:
        n_coarse = 0
    n_s = t.shape[1]
    pts = o[:, None, :] + d[:, None, :] * t[..., None]  # [r, S, 3]
    res = field_query(pts.reshape(-1, 3), d.repeat_interleave(n_s, 0))
    w = volume.render_weights(res["sigma"].view(t.shape), t, delta=delta)  # [r, S]
    channels = {k: v.view(len(idx), n_s, -1) for k, v in res.items() if k not in SKIP_CHANNELS}
    comp = volume.composite(w, channels)
    acc = volume.opacity(w)  # [r]
    depth = volume.expected_depth(w, t) / acc.clamp_min(1e-6)
    for name, value in comp.items():
        if name == "rgb":
            value = volume.over_background(value, acc, bg[idx])
            out[name] = bg.index_put((idx,), value)
        else:
            full = torch.zeros(n_rays, value.shape[-1], device=value.device, dtype=value.dtype)
            out[name] = full.index_put((idx,), value)
    out["opacity"] = out["opacity"].index_put((idx,), acc)
    out["depth"] = out["depth"].index_put((idx,), depth)
    out["samples"] = torch.tensor(n_coarse + t.numel())
    if keep_weights:
        out.update(weights=w, t=t, delta=delta)
    return out


def render_rays_chunked(
    field_query: FieldQuery,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    sampler,
    background=None,
    chunk: int = 16384,
) -> dict[str, torch.Tensor]:
    """`render_rays` without gradients, `chunk` rays at a time; results concatenated."""
    chunks: list[dict[str, torch.Tensor]] = []
    samples = 0
    with torch.no_grad():
        for start in range(0, origins.shape[0], chunk):
            res = render_rays(
                field_query,
                origins[start : start + chunk],
                dirs[start : start + chunk],
                sampler,
                background,
            )
            samples += int(res.pop("samples"))
            chunks.append(res)
    # A chunk where no ray hits has no extra channels (their width is unknown there): zeros.
    widths = {k: v.shape[1:] for res in chunks for k, v in res.items()}
    out = {}
    for k, shape in widths.items():
        out[k] = torch.cat(
            [
                res[k] if k in res else res["opacity"].new_zeros((len(res["opacity"]), *shape))
                for res in chunks
            ]
        )
    out["samples"] = torch.tensor(samples)
    return out


def render_image(
    camera,
    field_query: FieldQuery,
    sampler,
    background=None,
    chunk: int = 16384,
    device: torch.device | None = None,
    supersample: int = 1,
    subpixels: tuple[str, ...] = (),
) -> dict[str, np.ndarray]:
    """One camera -> {"rgb" [H, W, 3], "opacity" [H, W], "depth" [H, W] (ray distance),
    "z" [H, W] (camera depth), other channels [H, W, C]} as float32 numpy, without gradients.

    `supersample` s > 1: every channel is the mean of s x s rays spread evenly over each pixel
    (a box filter, as a camera pixel integrates light; s^2 times the rays); the depths are
    weighted by the rays' opacities (the depth of what the pixel sees). The channels named in
    `subpixels` also come unfiltered, as "NAME_subpixels" [s * s, H, W, C]: the s x s images of
    one ray per pixel, each at its own offset within the pixel (for a non-linear step, such as
    a texture edit's compositor, that must act on each before the box filter)."""
    device = device or torch.device("cpu")
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1 (got {supersample})")
    h, w = camera.height, camera.width
    fine = camera.resized(w * s, h * s) if s > 1 else camera
    o, d = fine.rays()
    o = torch.from_numpy(o).to(device)
    d = torch.from_numpy(d).to(device)
    res = render_rays_chunked(field_query, o, d, sampler, background, chunk)
    res["z"] = res["depth"] * torch.from_numpy(fine.z_per_unit_distance()).to(res["depth"])
    depths = ("depth", "z") if s > 1 else ()
    for k in depths:
        res[k] = res[k] * res["opacity"]  # divided by the pixel's mean opacity below
    out = {}
    for k, v in res.items():
        if k in ("samples", "hit"):
            continue
        v = v.detach().float().cpu().numpy().reshape(h, s, w, s, -1)
        if k in subpixels:  # [s * s, H, W, C]: image (i, j) holds ray (i, j) of every pixel
            out[f"{k}_subpixels"] = v.transpose(1, 3, 0, 2, 4).reshape(s * s, h, w, -1)
        v = v.mean(axis=(1, 3))
        out[k] = v if res[k].ndim == 2 else v[..., 0]
    for k in depths:
        out[k] = np.where(out["opacity"] > 0, out[k] / np.maximum(out["opacity"], 1e-6), 0.0)
    out["samples_per_pixel"] = np.float32(int(res["samples"]) / (h * w))
    return out
