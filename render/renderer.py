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
from render.sampler import RayHits, sampler_window

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


def sample_hits(
    sampler,
    hits: RayHits,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    sigma_at: Callable[[torch.Tensor, torch.Tensor], torch.Tensor],
    perturb: bool = False,
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor, int]:
    """Sample distances (t, delta) [r, S] along the hit rays `hits` (origins, dirs [r, 3]),
    refined by the sampler's importance pass when it has one, from the coarse samples'
    densities `sigma_at(points [M, 3], dirs [M, 3]) -> [M]` (no gradient); also the number of
    coarse field queries that pass made (0 without one)."""
    t, delta = sampler.sample(hits, perturb, generator)
    if not getattr(sampler, "n_importance", 0):
        return t, delta, 0
    with torch.no_grad():
        pts = origins[:, None, :] + dirs[:, None, :] * t[..., None]
        sigma = sigma_at(pts.reshape(-1, 3), dirs.repeat_interleave(t.shape[1], 0))
        w = volume.render_weights(sigma.view(t.shape), t, delta=delta)
    t, delta = sampler.importance(hits, t, w, perturb, generator)
    return t, delta, w.numel()


def render_rays(
    field_query: FieldQuery,
    origins: torch.Tensor,
    dirs: torch.Tensor,
    sampler,
    background=None,
    hits: RayHits | None = None,
    perturb: bool = False,
    generator: torch.Generator | None = None,
) -> dict[str, torch.Tensor]:
    """origins, dirs [R, 3] -> {"rgb" [R, 3] over background, "opacity" [R], "depth" [R],
    other channels [R, C], "hit" [R] bool, "samples" (field queries made)}.

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
    t, delta, n_coarse = sample_hits(
        sampler, sub, o, d, lambda x, v: field_query(x, v)["sigma"], perturb, generator
    )  # [r, S]
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


def _scatter_window(res: dict, chosen: torch.Tensor, camera, background) -> dict:
    """`render_rays_chunked` results of the pixels `chosen` [N] (row-major indices) -> the
    same for every pixel of `camera`, the others as rays that miss."""
    n = camera.height * camera.width
    zeros = torch.zeros(n, device=chosen.device)
    full = {"rgb": _background(background, n, zeros).clone(), "opacity": zeros, "depth": zeros}
    for k, v in res.items():
        if k == "samples":
            full[k] = v
        else:
            base = full[k] if k in full else v.new_zeros((n, *v.shape[1:]))
            full[k] = base.index_copy(0, chosen, v)
    return full


EDGE_SPREAD = 0.05  # a pixel's sub-ray opacities differing by more: a silhouette crosses it


def render_image(
    camera,
    field_query: FieldQuery,
    sampler,
    background=None,
    chunk: int = 16384,
    device: torch.device | None = None,
    supersample: int = 1,
    subpixels: tuple[str, ...] = (),
    edge_supersample: int | None = None,
) -> dict[str, np.ndarray]:
    """One camera -> {"rgb" [H, W, 3], "opacity" [H, W], "depth" [H, W] (ray distance),
    "z" [H, W] (camera depth), other channels [H, W, C]} as float32 numpy, without gradients.

    `supersample` s > 1: every channel is the mean of s x s rays spread evenly over each pixel
    (a box filter, as a camera pixel integrates light; s^2 times the rays); the depths are
    weighted by the rays' opacities (the depth of what the pixel sees). A silhouette crossing a
    pixel (its s x s rays' opacities differ by more than EDGE_SPREAD) makes the pixel's mean
    converge slowly with s: those pixels are rendered again with `edge_supersample` t x t rays
    (default 2 s; s or less: off), a few percent of the pixels ("rendered_again" [H, W] bool
    says which). The channels named in `subpixels` also come unfiltered, as "NAME_subpixels"
    [s * s, H, W, C]: the s x s images of one ray per pixel, each at its own offset within the
    pixel (for a non-linear step, such as a texture edit's compositor, that must act on each
    before the box filter); they are the s x s rays even where the pixel was rendered again."""
    device = device or torch.device("cpu")
    s = int(supersample)
    if s < 1:
        raise ValueError(f"supersample must be >= 1 (got {supersample})")
    t = 2 * s if edge_supersample is None else int(edge_supersample)
    h, w = camera.height, camera.width
    fine = camera.resized(w * s, h * s) if s > 1 else camera
    res, samples, scalar = _render_pixels(
        fine, None, field_query, sampler, background, chunk, device, s > 1
    )
    out = {}
    for k, v in res.items():
        v = v.reshape(h, s, w, s, -1)
        if k in subpixels:  # [s * s, H, W, C]: image (i, j) holds ray (i, j) of every pixel
            out[f"{k}_subpixels"] = v.transpose(1, 3, 0, 2, 4).reshape(s * s, h, w, -1)
        out[k] = v.mean(axis=(1, 3))
    again = np.zeros((h, w), bool)
    if s > 1 and t > s:
        sub_opacity = res["opacity"].reshape(h, s, w, s)
        again = sub_opacity.max(axis=(1, 3)) - sub_opacity.min(axis=(1, 3)) > EDGE_SPREAD
        rows, cols = np.nonzero(again)
        if len(rows):
            v, u = np.mgrid[0:t, 0:t]  # the t x t rays' places in a pixel, row by row
            offsets = (np.stack([u.ravel(), v.ravel()], -1) + 0.5) / t  # [t^2, 2] (u, v)
            pixels = np.stack([cols, rows], -1)[:, None, :] + offsets  # [E, t^2, 2] (u, v)
            edge, more, _ = _render_pixels(
                camera, pixels.reshape(-1, 2), field_query, sampler, background, chunk, device
            )
            samples += more
            for k, v in edge.items():
                out[k][rows, cols] = v.reshape(len(rows), t * t, -1).mean(axis=1)
    for k in scalar:
        out[k] = out[k][..., 0]
    if s > 1:
        for k in ("depth", "z"):
            out[k] = np.where(out["opacity"] > 0, out[k] / np.maximum(out["opacity"], 1e-6), 0.0)
    out["rendered_again"] = again
    out["samples_per_pixel"] = np.float32(samples / (h * w))
    return out


def _render_pixels(
    camera, pixels, field_query, sampler, background, chunk, device, weigh_depths=True
) -> tuple[dict[str, np.ndarray], int, set[str]]:
    """The rays through `pixels` [N, 2] (None: every pixel centre) -> (each channel [N, C] as
    float32 numpy, "z" the camera depth; with `weigh_depths` the depths multiplied by the
    opacity, to box-filter them; the field samples taken; the channels of one value, C = 1).
    Of a whole image only the sampler's `pixel_window` is rendered: the rays outside it miss
    (the background colour, zero elsewhere)."""
    chosen = None
    window = sampler_window(sampler, camera) if pixels is None else None
    if window is not None:
        chosen, pixels = camera.window_pixels(window)  # [N], [N, 2]
    o, d = camera.rays(pixels)
    res = render_rays_chunked(
        field_query,
        torch.from_numpy(o).to(device),
        torch.from_numpy(d).to(device),
        sampler,
        background,
        chunk,
    )
    if chosen is not None:
        res = _scatter_window(res, torch.from_numpy(chosen).to(device), camera, background)
        pixels = None
    res["z"] = res["depth"] * torch.from_numpy(camera.z_per_unit_distance(pixels)).to(res["depth"])
    samples = int(res.pop("samples"))
    res.pop("hit", None)
    out = {}
    for k, v in res.items():
        if weigh_depths and k in ("depth", "z"):
            v = v * res["opacity"]
        v = v.detach().float().cpu().numpy()
        out[k] = v.reshape(len(v), -1)
    return out, samples, {k for k, v in res.items() if v.ndim == 1}
