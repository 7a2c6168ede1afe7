"""The proxy refined by the template field (DESIGN.md section 4, the NeuS-style refine loop).

The fitted field's depth is usually better than the proxy it was fitted around (visual hull +
stereo miss concavities, stereo is noisy): march each training view's rays through the fit's
own sampler (so only the band the field was trained in, plus its coarse samples, is seen), keep
a depth where the opacity is >= `min_opacity` (inside the capture mask when there are masks;
optionally within `max_offset` of the current proxy along the ray), and fuse those depth maps
with the same TSDF and cleaning as the proxy_mesh stage (`recon.proxy_mesh.build_proxy`).

A pixel's depth is where its accumulated opacity first reaches `depth_level` (`ray_depths`), not
the renderer's expected depth: a density field's opacity ramps up behind the surface, which puts
the expected (and the median) depth behind it (spot, 400 steps: median +0.008 run units, about a
pixel footprint; a tail of 6 % of pixels > 0.03 behind, dragged by the wide coarse bins); the
0.2-crossing sits near the onset (median +0.004, tail 2 %).

The current proxy, seen from the closing views, closes what the field did not see (the underside
of a turntable object). With `carve` the field's views erase the old proxy where they see past
it: every real view is integrated into all TSDF blocks, its free space in front of the surface
and its mask-background pixels clearing what the old proxy put there (a hull spanning a
concavity); without it the old surface survives wherever it lies beyond the truncation band (and
the TSDF block) of the new depth and inside the silhouettes.

`refine_proxy(...) -> (mesh, stats)`; `refine_run(run, field, sampler, cfg)` loads a run's
training views, masks, proxy and proxy settings (recon_state.json) and calls it. Neither writes
anything: the caller decides whether the new proxy replaces proxy_mesh.ply.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, replace
from pathlib import Path

import cv2
import numpy as np
import torch

from recon.proxy_mesh import ProxyParams, build_proxy, closing_depths, tsdf_voxel
from recon.rundir import RunDir
from recon.selfcheck import resized_view
from render.cameras import Camera
from render.configs import option
from render.errors import SineError
from render.metrics import mask_iou
from render.raycast import MeshRaycaster, mesh_arrays

# Separate parts of a refined proxy kept down to this fraction of the largest one's triangles:
# the carving can cut a real part off at a thin joint (the dinosaur's hand before its belly,
# 1.3 %), which recon's --min-component 0.02 drops with its band; TSDF specks stay below 0.1 %.
REFINE_MIN_COMPONENT = 0.002
EMPTY_OPACITY = 0.1  # without masks, pixels rendered below this opacity count as seen empty


@dataclass
class RefineConfig:
    """Options of the proxy refine loop (a new proxy from the field's rendered depth)."""

    refine_scale: float = option(
        1.0,
        "refine: render the training views at this fraction of their size (the TSDF voxel "
        "grows with the pixel footprint: 0.5 is 4x faster but coarser)",
        low=0.05,
        high=1.0,
    )
    refine_views: int = option(0, "refine: training views rendered, evenly spaced (0 = all)", low=0)
    refine_min_opacity: float = option(
        0.5, "refine: pixels rendered at least this opaque give depth", low=0.0, high=1.0
    )
    refine_depth_level: float = option(
        0.2,
        "refine: a pixel's depth is where its accumulated opacity first reaches this (0.5 = "
        "the median depth; lower = nearer the density's onset, less biased behind the surface "
        "by a soft field); 0 = the expected depth",
        low=0.0,
        high=1.0,
    )
    refine_max_offset: float = option(
        0.0,
        "refine: drop depth farther than this (run units, along the ray) from the current "
        "proxy (0 = keep all)",
        low=0.0,
    )
    refine_carve: bool = option(
        True,
        "refine: the field's views erase the old proxy where they see past it (free space in "
        "front of their surface, mask background)",
    )
    refine_min_component: float = option(
        REFINE_MIN_COMPONENT,
        "refine: separate parts of the fused proxy are kept down to this fraction of the "
        "largest one's triangles (recon's --min-component 0.02 drops real parts the carving "
        "cut off at a thin joint; `sine fit --refine-min-component`)",
        low=0.0,
        high=1.0,
    )
    refine_chunk: int = option(16384, "refine: rays per rendering chunk", low=1)


def view_subset(n: int, count: int) -> list[int]:
    """`count` indices evenly spaced over range(n) (all of them when count is 0 or >= n)."""
    if count <= 0 or count >= n:
        return list(range(n))
    return sorted({int(round(x)) for x in np.linspace(0, n - 1, count)})


def scaled(cam: Camera, mask: np.ndarray | None, scale: float):
    """The camera and its mask [H, W] bool at `scale` of the size (mask by area, >= half)."""
    if scale == 1.0:
        return cam, mask
    return resized_view(
        cam, mask, max(1, round(cam.width * scale)), max(1, round(cam.height * scale))
    )


def ray_depths(
    field, sampler, origins: torch.Tensor, dirs: torch.Tensor, level: float = 0.5
) -> dict[str, torch.Tensor]:
    """Rays [R, 3] -> {"opacity" [R], "expected" [R] (ray distance, normalised by the opacity),
    "level" [R] (distance where the accumulated opacity reaches `level`, inf where it never
    does)}, through `sampler` as `render.renderer.render_rays` samples (importance pass
    included), without gradients. `field.density(points)` when the field has it (no colour is
    computed), else `field(points, dirs)["sigma"]`.

    The level crossing is interpolated inside the sample's bin (weight spread evenly over
    [t - delta/2, t + delta/2], exact for midpoint samples in their bins). A soft density (a
    ramp behind the surface) puts the expected and the median (level 0.5) depth behind the
    surface; lower levels lie nearer its onset (module doc).
    """
    from render import volume
    from render.renderer import sample_hits

    n = origins.shape[0]
    out = {
        "opacity": torch.zeros(n),
        "expected": torch.zeros(n),
        "level": torch.full((n,), float("inf")),
    }
    with torch.no_grad():
        hits = sampler.cast(origins, dirs)
        idx = torch.nonzero(hits.hit)[:, 0]
        if idx.numel() == 0:
            return out
        sub, o, d = hits[idx], origins[idx], dirs[idx]
        density = getattr(field, "density", None)  # sigma alone: no colour head

        def sigma_at(points, point_dirs):  # [M, 3] -> [M]
            if density is not None:
                return density(points).float()
            return field(points, point_dirs)["sigma"].float()

        t, delta, _ = sample_hits(sampler, sub, o, d, sigma_at)  # [r, S]
        pts = o[:, None, :] + d[:, None, :] * t[..., None]  # [r, S, 3]
        sigma = sigma_at(pts.reshape(-1, 3), d.repeat_interleave(t.shape[1], 0))
        w = volume.render_weights(sigma.view(t.shape), t, delta=delta)  # [r, S]
        acc = w.sum(-1)  # [r]
        cum = torch.cumsum(w, -1)  # [r, S]
        i = torch.searchsorted(cum, torch.full((len(idx), 1), level)).clamp_max(t.shape[1] - 1)
        before = torch.where(
            i > 0, cum.gather(1, (i - 1).clamp_min(0)), torch.zeros_like(acc[:, None])
        )
        w_i, t_i, d_i = w.gather(1, i), t.gather(1, i), delta.gather(1, i)
        frac = ((level - before) / w_i.clamp_min(1e-12)).clamp(0, 1)
        crossing = (t_i - 0.5 * d_i + frac * d_i)[:, 0]
        out["opacity"][idx] = acc.cpu()
        out["expected"][idx] = ((w * t).sum(-1) / acc.clamp_min(1e-6)).cpu()
        out["level"][idx] = torch.where(
            acc >= level, crossing, torch.full_like(acc, float("inf"))
        ).cpu()
    return out


def render_depth(
    field,
    sampler,
    cam: Camera,
    cfg: RefineConfig,
    device: torch.device | None = None,
    pixels: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """One camera -> opacity [H, W], ray distance [H, W] (the `refine_depth_level` crossing,
    or the expected distance when it is 0; inf where the level is never reached), camera z
    [H, W] of that distance. `pixels` [H, W] bool: only those are rendered (the others read
    opacity 0, distance inf)."""
    origins, dirs = (torch.from_numpy(a).to(device or "cpu") for a in cam.rays())
    shape = (cam.height, cam.width)
    chosen = None
    if pixels is not None:
        chosen = torch.from_numpy(np.flatnonzero(pixels)).to(origins.device)
        origins, dirs = origins[chosen], dirs[chosen]
    level = cfg.refine_depth_level or 0.5
    opacity, distance = [torch.zeros(0)], [torch.zeros(0)]
    for start in range(0, len(origins), cfg.refine_chunk):
        part = slice(start, start + cfg.refine_chunk)
        res = ray_depths(field, sampler, origins[part], dirs[part], level)
        opacity.append(res["opacity"])
        distance.append(res["level"] if cfg.refine_depth_level else res["expected"])
    opacity, t = torch.cat(opacity), torch.cat(distance)
    if chosen is not None:  # back into the image
        opacity = torch.zeros(shape[0] * shape[1]).index_copy(0, chosen.cpu(), opacity)
        t = torch.full((shape[0] * shape[1],), float("inf")).index_copy(0, chosen.cpu(), t)
    opacity, t = opacity.numpy().reshape(shape), t.numpy().reshape(shape)
    z = t * cam.z_per_unit_distance().reshape(shape)
    return opacity, t, z


def field_depth(
    field,
    sampler,
    cam: Camera,
    mask: np.ndarray | None,
    cfg: RefineConfig,
    proxy: MeshRaycaster | None = None,
    device: torch.device | None = None,
) -> tuple[np.ndarray, np.ndarray, dict]:
    """One view -> camera-z depth [H, W] for `fuse_tsdf` (0 unknown; np.inf seen empty when
    carving), the field's silhouette [H, W] bool and counts.

    Kept: opacity >= min_opacity, inside the (1-pixel dilated) mask, within max_offset of the
    proxy's hit along the ray (rays missing the proxy are kept). Seen empty: outside the dilated
    mask, or (no mask) rendered below EMPTY_OPACITY. With a mask only the dilated mask's pixels
    are rendered (nothing outside it could be kept), so the silhouette is the field's inside it.
    """
    near = None
    if mask is not None:
        near = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
    opacity, t, z = render_depth(field, sampler, cam, cfg, device, pixels=near)
    silhouette = opacity >= cfg.refine_min_opacity
    keep = silhouette & np.isfinite(z) & (z > 0)
    shift = np.zeros(0, np.float32)
    if proxy is not None:
        t_proxy = proxy.cast_camera(cam).t.reshape(z.shape)
        both = keep & np.isfinite(t_proxy)
        shift = t[both] - t_proxy[both]
        if cfg.refine_max_offset > 0:
            far = np.zeros_like(keep)
            far[both] = np.abs(shift) > cfg.refine_max_offset
            keep &= ~far
    depth = np.where(keep, z, 0.0).astype(np.float32)
    if cfg.refine_carve:
        empty = ~near if near is not None else opacity < EMPTY_OPACITY
        depth[empty] = np.inf
    counts = {
        "kept": int(keep.sum()),
        "silhouette": int(silhouette.sum()),
        "mask": int(mask.sum()) if mask is not None else None,
        "shift": shift,
    }
    return depth, silhouette, counts


def silhouette_ious(mesh, cameras: list[Camera], masks: list[np.ndarray]) -> list[float]:
    """IoU of the mesh's ray-cast silhouette with each view's mask (recon.report style)."""
    caster = MeshRaycaster(mesh)
    return [
        mask_iou(mask, caster.silhouette(cam)) for cam, mask in zip(cameras, masks, strict=True)
    ]


def refine_proxy(
    field,
    sampler,
    cameras: list[Camera],
    masks: list[np.ndarray] | None,
    proxy_cfg: ProxyParams,
    old_proxy,
    cfg: RefineConfig | None = None,
    closing_mesh=None,
    device: torch.device | None = None,
    progress: bool = True,
    old_ious: list[float] | None = None,
):
    """A new proxy from the field's depth in `cameras` (training views, full size; `masks`
    [H, W] bool per camera or None) -> (legacy o3d TriangleMesh, stats). `field(points [M, 3],
    dirs [M, 3])["sigma"]` [M]; `sampler`: the fit's (render.sampler BandSampler/UniformSampler).

    `old_proxy`: the current proxy (any mesh `render.raycast.mesh_arrays` takes): it closes
    what the field did not see (unless `closing_mesh` is given, e.g. the visual hull), the
    max_offset test is against it, and the stats compare with it. stats: silhouette IoU with the
    masks (mean/min over all `cameras`, old and new; `silhouette_ious_after` the new one's per
    camera, which a next round can pass as `old_ious` rather than cast the same silhouettes
    again), triangles, whether the new one is closed, pixels kept (of the masks; of the field's
    silhouette, inside the dilated masks when there are masks), how far the
    field's depth lies from the old proxy (median / 90th percentile of |t_field - t_proxy|),
    the TSDF voxel used, seconds (rendering, fusion, total).
    """
    cfg = cfg or RefineConfig()
    if masks is not None and len(masks) != len(cameras):
        raise SineError("refine_proxy: one mask per camera (or no masks at all)")
    t0 = time.perf_counter()
    old_v, old_f = mesh_arrays(old_proxy)
    if len(old_f) == 0:
        raise SineError("the proxy to refine has no triangles; re-run `sine recon`")
    caster = MeshRaycaster((old_v, old_f))
    chosen = view_subset(len(cameras), cfg.refine_views)
    small_cams, depths, fuse_masks, shifts = [], [], [], []
    kept = silhouette_px = mask_px = 0
    was_training = getattr(field, "training", False)
    if hasattr(field, "eval"):
        field.eval()
    try:
        for i in chosen:
            cam, mask = scaled(cameras[i], None if masks is None else masks[i], cfg.refine_scale)
            depth, silhouette, counts = field_depth(field, sampler, cam, mask, cfg, caster, device)
            small_cams.append(cam)
            depths.append(depth)
            fuse_masks.append(mask if mask is not None else silhouette)
            shifts.append(counts["shift"])
            kept += counts["kept"]
            silhouette_px += counts["silhouette"]
            mask_px += counts["mask"] or 0
    finally:
        if was_training:
            field.train()
    t_render = time.perf_counter() - t0
    if kept == 0:
        raise SineError(
            "the field renders no opaque pixel inside the masks: nothing to refine the proxy with"
            " (is the template fitted?)"
        )
    cv, cf = mesh_arrays(closing_mesh) if closing_mesh is not None else (old_v, old_f)
    mesh = build_proxy(
        small_cams,
        depths,
        fuse_masks,
        replace(proxy_cfg, min_component=cfg.refine_min_component),
        closing=closing_depths(cv, cf),
        carve=cfg.refine_carve,
        progress=progress,
    )
    t_total = time.perf_counter() - t0
    shift = np.abs(np.concatenate(shifts)) if shifts else np.zeros(0)
    stats = {
        "refine_views": len(chosen),
        "refine_scale": cfg.refine_scale,
        "refine_voxel_size": tsdf_voxel(small_cams, proxy_cfg.voxel_size),
        "refine_pixels_kept": kept,
        "refine_kept_of_mask": kept / mask_px if mask_px else None,
        "refine_kept_of_silhouette": kept / silhouette_px if silhouette_px else None,
        "refine_shift_median": float(np.median(shift)) if len(shift) else None,
        "refine_shift_p90": float(np.percentile(shift, 90)) if len(shift) else None,
        "proxy_triangles_before": len(old_f),
        "proxy_triangles_after": len(mesh.triangles),
        # closed as recon.proxy_mesh.mesh_stats counts it (Open3D's is_watertight adds a
        # self-intersection test: 3.3 s on a 40k-triangle proxy, per round)
        "proxy_closed_after": bool(mesh.is_edge_manifold(False) and mesh.is_vertex_manifold()),
        "seconds_render": t_render,
        "seconds_fuse": t_total - t_render,
    }
    if masks is not None:
        known = old_ious is not None and len(old_ious) == len(cameras)
        before = old_ious if known else silhouette_ious((old_v, old_f), cameras, masks)
        after = silhouette_ious(mesh, cameras, masks)
        stats.update(
            silhouette_iou_before=float(np.mean(before)),
            silhouette_iou_after=float(np.mean(after)),
            silhouette_iou_min_before=float(np.min(before)),
            silhouette_iou_min_after=float(np.min(after)),
            silhouette_ious_after=after,
        )
    stats["seconds"] = time.perf_counter() - t0
    return mesh, stats


def run_proxy_params(run: RunDir) -> ProxyParams:
    """The proxy settings the run's proxy_mesh stage used (recon_state.json), else recon's
    defaults."""
    from recon.recon_config import ReconConfig, proxy_params
    from render.io import read_json

    cfg = ReconConfig()
    path = run.root / "recon_state.json"
    used = read_json(path).get("options", {}).get("proxy_mesh", {}) if path.is_file() else {}
    for key, value in used.items():
        if hasattr(cfg, key):
            setattr(cfg, key, value)
    return proxy_params(cfg)


def refine_run(
    run: RunDir,
    field,
    sampler,
    cfg: RefineConfig | None = None,
    device: torch.device | None = None,
    progress: bool = True,
    proxy: Path | None = None,
    old_ious: list[float] | None = None,
):
    """`refine_proxy` on a run: its training views (masks when every one has a mask), its
    proxy (`proxy`, default proxy_mesh.ply; `old_ious` its silhouette IoUs when known) and
    proxy settings -> (mesh, stats). Writes nothing."""

    from render.io import read_mask

    cams = [c for c in run.load_cameras().frames if c.split == "train"]
    if not cams:
        raise SineError(f"{run.cameras} has no training views")
    paths = [run.mask_path(c.name) for c in cams]
    masks = [read_mask(p) for p in paths] if all(p.is_file() for p in paths) else None
    if masks is not None:
        cams = [
            c if m.shape == (c.height, c.width) else c.resized(m.shape[1], m.shape[0])
            for c, m in zip(cams, masks, strict=True)
        ]
    old = run.read_proxy(proxy)
    params = run_proxy_params(run)
    return refine_proxy(
        field,
        sampler,
        cams,
        masks,
        params,
        old,
        cfg,
        device=device,
        progress=progress,
        old_ious=old_ious,
    )
