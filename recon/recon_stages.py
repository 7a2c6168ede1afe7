"""The stages of `sine recon` besides ingest and poses (recon.ingest, recon.recon_poses): masks,
normalize, depth, proxy_mesh and report, as functions of the Pipeline (`pipe`) that its
`stage_X` methods call."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from recon.recon_config import ReconConfig, proxy_params
from render.errors import SineError
from render.io import atomic_path, read_depth, write_depth

if TYPE_CHECKING:
    from recon.pipeline import Pipeline


# what the normalize stage keeps of its inputs until it is recorded
GIVEN_CAMERAS, GIVEN_DEPTH = "cameras_given.json", ".given.npy"


def partial_capture_message(stats: dict, views: int, source: str, cfg: ReconConfig) -> str:
    """The depth stage's stop when too few masked pixels get depth (an open visual hull)."""
    cut = views - stats.get("hull_complete_views", 0)
    stereo = (
        f"stereo filled {stats.get('stereo_open_pixel_fraction', 0.0):.0%} of those pixels"
        if source == "visual_hull+stereo"
        else "stereo was not used (--depth-method visual_hull)"
    )
    return (
        f"only {stats['depth_pixel_fraction']:.0%} of the masked pixels got depth (< "
        f"{cfg.min_depth_fraction:.0%}, --min-depth-fraction): the views do not bound the object. "
        f"{cut} of {views} views show it cut by the image border, so the visual hull is open on "
        f"{stats.get('hull_open_fraction', 0.0):.0%} of its surface (nothing carves what lies "
        f"outside those frames) and {stereo}. Try: add views that show the whole object (at "
        "least two, from different sides), give the capture's depth maps, or lower "
        "--min-depth-fraction to accept a partial proxy"
    )


def stage_masks(pipe: Pipeline) -> dict:
    from recon.masks import MaskParams, compute_masks

    views = pipe.views()
    redo = set(pipe.state["stages"].get("masks", {}).get("auto", [])) if pipe.force else set()
    params = MaskParams(
        border_fraction=pipe.cfg.mask_border_fraction,
        lightness_weight=pipe.cfg.mask_lightness_weight,
        grabcut_iterations=pipe.cfg.mask_grabcut_iterations,
        method=pipe.cfg.mask_method,
    )
    names = [r["name"] for r in views]
    cameras = None  # the capture's own cameras make saliency masks multi-view consistent
    if pipe.run.load_captures().get("poses") and pipe.run.cameras.is_file():
        by_name = {c.name: c for c in pipe.run.load_cameras().frames}
        if not pipe.ignore_poses and all(n in by_name for n in names):
            cameras = [by_name[n] for n in names]
    if pipe.cfg.object_box is not None:
        from recon.object_select import select_masks

        return select_masks(pipe.run, views, cameras, pipe.cfg.object_view, pipe.cfg.object_box)
    out = compute_masks(
        [pipe.run.image_path(n) for n in names],
        [pipe.run.mask_path(n) for n in names],
        params,
        redo=redo,
        cameras=cameras,
    )
    coverage = list(out["coverage"].values())
    methods = list(out["methods"].values())
    if out["flagged"]:
        print(
            f"[recon] masks: {len(out['flagged'])} mask(s) disagree with the visual hull of "
            f"the others: {', '.join(out['flagged'][:5])}; check them in masks/"
        )
    return {
        "auto": out["auto"],
        "mask_coverage_mean": float(np.mean(coverage)),
        "mask_coverage_min": float(np.min(coverage)),
        "masks_automatic": len(out["auto"]),
        "masks_given": len(names) - len(out["auto"]),
        "masks_keying": methods.count("keying"),
        "masks_saliency": methods.count("saliency"),
        "masks_keying_unreliable": out["keying_unreliable"],
        "masks_flagged": out["flagged"],
        "masks_keyed_hull_iou": out["keyed_hull_iou"],
    }


def stage_normalize(pipe: Pipeline) -> dict:
    from recon.normalize import apply_normalization, compute_normalization
    from render.cameras import load_cameras, save_cameras

    # the stage rewrites its own inputs: they are kept aside until it is recorded, so an
    # interrupted stage starts again from them (never from its half-written outputs)
    given = pipe.run.root / GIVEN_CAMERAS
    if not given.is_file():
        save_cameras(given, pipe.run.load_cameras())
    cams = load_cameras(given)
    norm, stats = compute_normalization(
        cams.frames, pipe.masks_for(cams.frames), pipe.cfg.target_radius
    )
    new = apply_normalization(cams, norm)
    for cam in cams.frames:  # depth follows the frame's units
        depth = pipe.run.depth_path(cam.name)
        kept = depth.with_name(depth.stem + GIVEN_DEPTH)
        if depth.is_file() and not kept.is_file():
            write_depth(kept, read_depth(depth))
        if kept.is_file():
            write_depth(depth, read_depth(kept) * np.float32(norm.scale))
    pipe.run.save_cameras(new)
    return {
        **stats,
        "normalization_scale": new.scale,
        "normalization_center": [float(x) for x in new.center],
    }


def _hull(pipe: Pipeline, cams, masks, fresh: bool = False):
    """The visual hull (recon.depth.HullMesh), cached in visual_hull.npz (the depth stage
    refreshes it)."""
    from recon.depth import read_hull, visual_hull

    path = pipe.run.root / "visual_hull.npz"
    saved = None if fresh else read_hull(path)
    if saved is not None:
        return saved
    hull = visual_hull(cams, masks, pipe.cfg.hull_resolution, pipe.cfg.hull_tolerance)
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as fh:
            np.savez(
                fh,
                vertices=hull.vertices,
                faces=hull.faces,
                voxel=hull.voxel,
                open_faces=hull.open_faces,
                complete_views=hull.complete_views,
            )
    return hull


def stage_depth(pipe: Pipeline) -> dict:
    from recon.depth import visual_hull_depth

    cams = pipe.run.load_cameras().frames
    by_name = {r["name"]: r for r in pipe.views()}
    method = pipe.cfg.depth_method
    have = all(by_name.get(c.name, {}).get("depth") for c in cams)
    poses = pipe.state["stages"].get("poses", {})
    if have and poses.get("dataset_depth_verified") is False:
        if method == "dataset":
            raise SineError(
                "--depth-method dataset: the capture's depth maps were dropped, they do not "
                f"agree with the estimated poses ({poses.get('dataset_depth_check')}); use "
                "--depth-method auto, or raise --dataset-depth-tolerance"
            )
        have = False
    if method == "dataset" and not have:
        raise SineError("--depth-method dataset: the capture has no depth for every view")
    (pipe.run.root / "visual_hull.npz").unlink(missing_ok=True)  # cams may have changed
    if method in ("auto", "dataset") and have:
        return {"depth_source": "dataset"}
    masks = pipe.masks_for(cams)
    hull = pipe._hull(cams, masks, fresh=True)
    depths, stats = visual_hull_depth(
        cams, masks, pipe.cfg.hull_resolution, pipe.cfg.hull_tolerance, hull=hull
    )
    source = "visual_hull"
    if method in ("auto", "visual_hull+stereo"):
        from recon.depth import hull_stereo_depth
        from render.io import read_image

        images = [read_image(pipe.run.image_path(c.name)) for c in cams]
        depths, more = hull_stereo_depth(
            cams,
            images,
            masks,
            depths,
            front_tol=2.0 * stats["hull_voxel_size"],
            max_behind=pipe.cfg.stereo_max_behind,
        )
        stats.update(more)
        source = "visual_hull+stereo"
    masked = sum(int(m.sum()) for m in masks)
    covered = sum(int((m & (d > 0)).sum()) for m, d in zip(masks, depths, strict=True))
    stats["depth_pixel_fraction"] = covered / max(masked, 1)
    if stats["depth_pixel_fraction"] < pipe.cfg.min_depth_fraction:
        raise SineError(partial_capture_message(stats, len(cams), source, pipe.cfg))
    for cam, depth in zip(cams, depths, strict=True):
        write_depth(pipe.run.depth_path(cam.name), depth)
    return {"depth_source": source, **stats}


def stage_proxy_mesh(pipe: Pipeline) -> dict:
    from recon.proxy_mesh import build_proxy, closing_depths, mesh_stats, write_mesh

    cams = pipe.run.load_cameras().frames
    depths = [read_depth(pipe.run.depth_path(c.name)) for c in cams]
    masks = pipe.masks_for(cams)
    closing = None
    if pipe.cfg.proxy_close_with_hull:
        hull = pipe._hull(cams, masks)
        closing = closing_depths(hull.vertices, hull.faces, hull.open_faces)
    params = proxy_params(pipe.cfg)
    mesh = build_proxy(cams, depths, masks, params, closing=closing, carve=pipe.cfg.proxy_carve)
    write_mesh(pipe.run.proxy_mesh, mesh)
    return {**mesh_stats(mesh), "proxy_closed_with_hull": closing is not None}


def stage_report(pipe: Pipeline) -> dict:
    from recon.report import write_report

    return write_report(
        pipe.run,
        pipe.state,
        pipe.cfg.contact_sheet_columns,
        pipe.thresholds(),
        accepted=pipe.cfg.accept_poor_poses,
    )
