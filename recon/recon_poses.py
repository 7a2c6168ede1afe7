"""The poses stage of `sine recon` and its helpers, as functions of the Pipeline (`pipe`) that
its methods of the same names call: the capture's own poses, structure from motion
(recon.poses) or the turntable model (recon.turntable), the self-check of the poses, and the
capture's depth maps brought into the poses' units."""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from recon.recon_config import ReconConfig
from render.cameras import Camera, CameraSet
from render.errors import SineError
from render.io import read_depth, read_mask

if TYPE_CHECKING:
    from recon.pipeline import Pipeline


def sfm_too_few(registered: int, total: int, cfg: ReconConfig) -> str:
    return (
        f"structure from motion registered only {registered} of {total} views "
        f"(< {cfg.min_registered_fraction:.0%}). Try: check the masks (masks/ in the run "
        "directory, or give --masks DIR), --turntable on for a turntable capture, capture with "
        "more overlap between neighbouring views (<= 10-15 degrees of turn) and more texture, "
        "or give known poses (transforms.json, COLMAP, ...)"
    )


def check_poses(pipe: Pipeline, cams, reprojection_px=None) -> dict:
    """The self-check of poses (recon.selfcheck) as a dict for the stage info."""
    from recon.selfcheck import check_poses

    masks = pipe.masks_for(cams)
    turntable = pipe.cfg.turntable == "on"
    verdict = check_poses(cams, masks, pipe.thresholds(), reprojection_px, turntable=turntable)
    if reprojection_px is None and verdict.numbers["hull_iou_mean"] == 0.0:
        from recon.visual_hull import UnboundedHull, hull_bounds

        try:  # the capture's own poses and an empty hull: a partial capture says so
            hull_bounds(cams, masks)
        except UnboundedHull:
            raise
        except SineError:
            pass  # the masks and cameras disagree: the self-check's verdict says it
    print(
        f"[recon] poses: self-check {verdict.verdict} (hull silhouette IoU mean "
        f"{verdict.numbers['hull_iou_mean']:.3f})"
    )
    return verdict.to_dict()


def stage_poses(pipe: Pipeline) -> dict:
    """Poses from the capture, SfM, or the turntable model (module doc of recon.turntable):
    `turntable` on = always; auto = when SfM registers too few views or its self-check
    fails and the views look like an ordered turntable sequence; off = SfM only."""
    captures = pipe.run.load_captures()
    views = pipe.views()
    if captures.get("poses") and pipe.run.cameras.is_file() and not pipe.ignore_poses:
        cams = pipe.run.load_cameras()
        return {
            "pose_source": "input",
            "registered_views": len(cams.frames),
            "total_views": len(views),
            "unregistered": [],
            "mean_reprojection_error_px": None,
            "self_check": pipe.check_poses(cams.frames),
        }
    mode = pipe.cfg.turntable
    try:
        info, frames, sfm = pipe.sfm_poses(views, partial=mode != "off")
    except SineError as exc:
        if mode == "off":
            raise
        info, frames, sfm = {"sfm_error": str(exc)}, [], None
    n = len(views)
    enough = bool(frames) and len(frames) >= pipe.cfg.min_registered_fraction * n
    check = pipe.check_poses(frames, info["mean_reprojection_error_px"]) if enough else None
    fallback = None
    if mode == "on":
        fallback = "--turntable on"
    elif not enough:
        fallback = f"SfM registered {len(frames)} of {n} views"
    elif check["verdict"] != "ok":
        fallback = "the SfM self-check failed"
    if fallback and mode == "auto":
        from recon.selfcheck import looks_like_turntable

        masks = [read_mask(pipe.run.mask_path(r["name"])) for r in views]
        if not looks_like_turntable(masks):
            print(f"[recon] poses: {fallback}; the views do not look like a turntable")
            fallback = None
    if fallback is None:
        if not enough:
            raise SineError(info.get("sfm_error") or sfm_too_few(len(frames), n, pipe.cfg))
        pipe.use_sfm(views, sfm, frames, info)
        info["self_check"] = check
        return info
    print(f"[recon] poses: turntable model ({fallback})")
    sfm_info = {
        "sfm_pose_source": info.get("pose_source"),
        "sfm_registered_views": info.get("registered_views", 0),
        "sfm_mean_reprojection_error_px": info.get("mean_reprojection_error_px"),
        "sfm_error": info.get("sfm_error"),
        "sfm_self_check": check,
    }
    turntable = pipe.turntable_poses(views, sfm)
    return {**turntable, "turntable_reason": fallback, **sfm_info}


def sfm_params(pipe: Pipeline, partial: bool):
    from recon.poses import SfmParams

    return SfmParams(
        camera_model=pipe.cfg.camera_model,
        exhaustive_below=pipe.cfg.exhaustive_below,
        sequential_overlap=pipe.cfg.sequential_overlap,
        min_registered_fraction=0.0 if partial else pipe.cfg.min_registered_fraction,
        mapper=pipe.cfg.mapper,
        seed=pipe.cfg.seed,
        peak_threshold=pipe.cfg.sfm_peak_threshold,
        num_threads=pipe.cfg.sfm_threads,
        estimate_affine_shape=pipe.cfg.sfm_affine_shape,
        domain_size_pooling=pipe.cfg.sfm_domain_size_pooling,
        guided_matching=pipe.cfg.sfm_guided_matching,
        final_ba=pipe.cfg.sfm_final_ba,
    )


def prior_intrinsics(pipe: Pipeline, views: list[dict]) -> dict[str, Camera]:
    """Intrinsics the capture carries (ingest keeps them per record unless
    --ignore-intrinsics): --ignore-poses drops only the extrinsics."""
    return {
        r["name"]: Camera(width=r["width"], height=r["height"], **r["intrinsics"])
        for r in views
        if r.get("intrinsics")
    }


def sfm_poses(pipe: Pipeline, views: list[dict], partial: bool = False):
    """Structure from motion on the views (recon.poses): stage info, the registered cameras
    at the working size and the SfmResult (nothing written yet: see `use_sfm`).
    `partial`: too few registered views is not an error here."""
    from recon.poses import prepare_sfm_images, run_sfm

    work = pipe.run.root / "sfm"
    sfm_views = []
    for r in views:
        source = Path(r["source"]) if r.get("source") and not r.get("undistorted") else None
        sfm_views.append(
            (r["name"], pipe.run.image_path(r["name"]), pipe.run.mask_path(r["name"]), source)
        )
    image_dir, mask_dir = prepare_sfm_images(
        sfm_views,
        work,
        pipe.cfg.sfm_max_image_size,
        min_object_px=pipe.cfg.sfm_min_object_px,
        max_upscale=pipe.cfg.sfm_max_upscale,
    )
    names = [r["name"] for r in views]
    result = run_sfm(
        image_dir,
        mask_dir,
        names,
        work,
        pipe.sfm_params(partial),
        intrinsics=pipe.prior_intrinsics(views),
    )
    sfm_width = int(cv2.imread(str(image_dir / names[0]), cv2.IMREAD_UNCHANGED).shape[1])
    by_name = {r["name"]: r for r in views}
    frames = [
        c.resized(by_name[c.name]["width"], by_name[c.name]["height"]).replace(
            split=by_name[c.name]["split"]
        )
        for c in result.cameras
    ]
    print(
        f"[recon] poses: registered {len(frames)} of {len(names)} views, mean reprojection "
        f"error {result.mean_reprojection_error_px:.3f} px"
    )
    info = {
        "pose_source": f"sfm ({result.mapper})",
        "sfm_models": result.num_models,
        "sfm_intrinsics": result.intrinsics,
        "sfm_image_width": sfm_width,
        "registered_views": len(frames),
        "total_views": len(names),
        "unregistered": result.unregistered,
        "mean_reprojection_error_px": result.mean_reprojection_error_px,
        "sparse_points": len(result.points),
    }
    return info, frames, result


def use_sfm(pipe: Pipeline, views: list[dict], result, frames: list[Camera], info: dict) -> None:
    """Writes the SfM cameras; dataset depth into SfM units when one scale fits it (else it
    is dropped, `verify_dataset_depth`); undistortion in place."""
    from recon.poses import depth_scale_to_sfm, undistort_depth_in_place, undistort_in_place

    by_name = {r["name"]: r for r in views}
    depth_paths = {
        r["name"]: pipe.run.depth_path(r["name"]) for r in views if by_name[r["name"]].get("depth")
    }
    if depth_paths:
        fit = depth_scale_to_sfm(
            result.observations,
            depth_paths,
            result.cameras,
            tolerance=pipe.cfg.dataset_depth_tolerance,
        )
        pipe.verify_dataset_depth(fit, list(depth_paths.values()), "sfm", info)
    if np.any(result.distortion != 0):
        for c in frames:
            undistort_in_place([pipe.run.image_path(c.name)], c, result.distortion, nearest=False)
            undistort_in_place([pipe.run.mask_path(c.name)], c, result.distortion, nearest=True)
            if info.get("dataset_depth_verified") and c.name in depth_paths:
                undistort_depth_in_place(depth_paths[c.name], c, result.distortion)
        info["undistorted_distortion"] = [float(x) for x in result.distortion]
    pipe.run.save_cameras(CameraSet(frames=frames, extra={"source_format": "sfm"}))


def verify_dataset_depth(
    pipe: Pipeline, fit, depth_paths: list[Path], poses: str, info: dict
) -> None:
    """The capture's depth maps into the units of the estimated poses when one scale fits
    them (recon.poses.DepthScaleFit); otherwise they are dropped (`dataset_depth_verified`
    false in the stage info: the depth stage then uses the visual hull and stereo)."""
    from recon.poses import rescale_depth

    info.update(fit.to_dict())
    if fit.consistent():
        rescale_depth(depth_paths, fit.factor)
        info[f"dataset_depth_to_{poses}_scale"] = fit.factor
        return
    print(
        f"[recon] poses: WARNING: the capture's depth maps do not agree with the {poses} "
        f"poses ({fit.summary()}; allowed {fit.tolerance:.1%}, --dataset-depth-tolerance): "
        "dropped, the depth stage uses the visual hull and stereo"
    )


def turntable_poses(pipe: Pipeline, views: list[dict], sfm) -> dict:
    """Every view posed by the turntable model (recon.turntable), seeded by the largest SfM
    model whose views are consistent; writes cameras.json; stage info."""
    from recon.selfcheck import check_poses
    from recon.turntable import TurntableParams, choose_seed, solve_turntable
    from render.device import torch_threads

    names = [r["name"] for r in views]
    by_name = {r["name"]: r for r in views}
    masks = [read_mask(pipe.run.mask_path(n)) for n in names]
    h, w = masks[0].shape
    prior = pipe.prior_intrinsics(views)
    seed = choose_seed(sfm.models if sfm else [], names, masks, pipe.thresholds())
    intrinsics = prior.get(names[0])
    if intrinsics is None and seed is not None:
        intrinsics = seed[0][0]  # SfM's estimate
    params = TurntableParams(
        step_deg=pipe.cfg.turntable_step, iterations=pipe.cfg.turntable_iterations
    )
    with torch_threads(pipe.cfg.sfm_threads):
        result = solve_turntable(
            masks,
            params,
            intrinsics=intrinsics.resized(w, h) if intrinsics is not None else None,
            seed=(([c.resized(w, h) for c in seed[0]], seed[1]) if seed is not None else None),
            names=names,
        )
    frames = [
        c.resized(by_name[c.name]["width"], by_name[c.name]["height"]).replace(
            split=by_name[c.name]["split"]
        )
        for c in result.cameras
    ]
    info = {
        "pose_source": "turntable",
        "turntable_init": result.init,
        "turntable_loss_px": round(result.loss_px, 4),
        "turntable_elevation_deg": round(result.elevation_deg, 3),
        "turntable_steps_deg": [round(float(x), 3) for x in np.diff(result.angles_deg)],
        "turntable_focal_refined": result.focal_refined,
        "turntable_angles_observable": result.angles_observable,
        "registered_views": len(frames),
        "total_views": len(views),
        "unregistered": [],
        "mean_reprojection_error_px": None,
    }
    depth_paths = [pipe.run.depth_path(n) for n in names if by_name[n].get("depth")]
    if depth_paths:
        fit = pipe.turntable_depth_scale(frames)
        pipe.verify_dataset_depth(fit, depth_paths, "turntable", info)
    pipe.run.save_cameras(CameraSet(frames=frames, extra={"source_format": "turntable"}))
    verdict = check_poses(frames, pipe.masks_for(frames), pipe.thresholds(), turntable=True)
    if not result.angles_observable:
        verdict.verdict = "poor"
        verdict.reasons.append(
            "the silhouettes do not determine the turntable's angles (turning views by 5 "
            "degrees changes nothing: a body of revolution?), so the poses are a guess"
        )
    print(
        f"[recon] poses: turntable self-check {verdict.verdict} (hull silhouette IoU mean "
        f"{verdict.numbers['hull_iou_mean']:.3f})"
    )
    info["self_check"] = verdict.to_dict()
    return info


def turntable_depth_scale(pipe: Pipeline, frames: list[Camera]):
    """The factor taking the capture's depth maps into the turntable poses' units
    (`DepthScaleFit`): a first guess from the visual hull's rim, then the ratio at which
    overlapping views' depth maps agree (recon.turntable.consistent_depth_ratios; the rim
    alone came out 3 % low on the toycar, its hull's voxels)."""
    from recon.poses import fit_depth_scale
    from recon.turntable import consistent_depth_ratios, rim_depth_ratios

    masks, depths = [], []
    for cam in frames:
        mask = read_mask(pipe.run.mask_path(cam.name))
        depth = read_depth(pipe.run.depth_path(cam.name))
        if depth.shape != mask.shape:
            depth = cv2.resize(depth, mask.shape[::-1], interpolation=cv2.INTER_NEAREST)
        masks.append(mask)
        depths.append(depth)
    tolerance = pipe.cfg.dataset_depth_tolerance
    rim = fit_depth_scale(rim_depth_ratios(frames, masks, depths), tolerance)
    if rim.factor is None:
        return rim
    fit = fit_depth_scale(consistent_depth_ratios(frames, masks, depths, rim.factor), tolerance)
    return fit if fit.factor is not None else rim
