"""`sine recon`: turntable-aware reconstruction as idempotent stages.

ingest -> masks -> poses -> normalize -> depth -> proxy_mesh -> report. Each stage reads and
writes run-directory artefacts (atomically) and records itself and the options it used (the
ReconConfig options whose help starts with its name, see `stage_options`) in
`recon_state.json`; a finished stage is skipped on the next run unless `force` is set or its
options changed (then it says which, and runs again). A stage that runs invalidates every stage
after it. The per-stage results become `recon_report.json`.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from recon.formats import FORMAT_VERSIONS, format_change
from recon.rundir import RunDir
from render.cameras import Camera, CameraSet
from render.configs import option, to_dict, validate, write_settings
from render.errors import SineError
from render.io import (
    atomic_path,
    read_depth,
    read_json,
    read_mask,
    remove_partial_writes,
    write_depth,
    write_json,
)
from render.locks import lock_folder

STAGES = ("ingest", "masks", "poses", "normalize", "depth", "proxy_mesh", "report")
# The prefix of a ReconConfig option's help text names the stage it belongs to.
_HELP_PREFIX = {"proxy_mesh": "proxy"}


@dataclass
class ReconConfig:
    """Options of `sine recon` (besides the ingest options)."""

    mask_border_fraction: float = option(
        0.04, "masks: width of the image border sampled for backdrop colours", low=0.0, high=0.5
    )
    mask_lightness_weight: float = option(
        0.35,
        "masks: weight of Lab lightness in the colour-keying distance (hue/chroma weigh 1)",
        low=0.0,
    )
    mask_grabcut_iterations: int = option(
        4, "masks: GrabCut iterations after colour keying (0 = keying only)", low=0
    )
    mask_method: str = option(
        "auto",
        "masks: keying = backdrop colour keying + GrabCut (plain backdrops); saliency = the "
        "img-focus saliency prior + GrabCut, made consistent across views by the visual hull "
        "when the capture brings its cameras (cluttered backgrounds); auto = saliency where "
        "keying is unreliable (the image border is not a few backdrop colours, the keyed "
        "mask covers the border or most of the image, or with the capture's cameras the keyed "
        "masks disagree with their visual hull)",
        choices=["auto", "keying", "saliency"],
    )
    camera_model: str = option(
        "SIMPLE_PINHOLE",
        "poses: COLMAP camera model shared by all views (with distortion the working images are undistorted)",
        choices=["SIMPLE_PINHOLE", "PINHOLE", "SIMPLE_RADIAL", "RADIAL"],
    )
    mapper: str = option(
        "auto",
        "poses: SfM mapper; auto = incremental, plus global when incremental leaves views out",
        choices=["auto", "incremental", "global"],
    )
    sfm_max_image_size: int = option(
        1600,
        "poses: SIFT runs on the source images (more precise than the working ones) up to this width",
        low=16,
    )
    exhaustive_below: int = option(
        60, "poses: match all pairs below this many views, else a cyclic window", low=0
    )
    sequential_overlap: int = option(
        10, "poses: neighbours on each side matched in the cyclic window", low=1
    )
    min_registered_fraction: float = option(
        0.7, "poses: fail when fewer views than this fraction register", low=0.0, high=1.0
    )
    sfm_min_object_px: float = option(
        400.0,
        "poses: upsample the SfM images (bicubic) until the object's median bounding-box "
        "diagonal reaches this many pixels (0 = never upsample)",
        low=0.0,
    )
    sfm_max_upscale: float = option(2.0, "poses: largest SfM upsampling factor", low=1.0)
    sfm_peak_threshold: float = option(
        0.002,
        "poses: SIFT peak (contrast) threshold; lower finds more, weaker features (small or "
        "low-contrast objects)",
        low=0.0,
    )
    sfm_threads: int = option(
        1,
        "poses: SfM threads; 1 = deterministic results, -1 = all cores (faster, results vary)",
        low=-1,
    )
    sfm_affine_shape: bool = option(
        False, "poses: SIFT with affine shape estimation (slower; wide baselines)"
    )
    sfm_domain_size_pooling: bool = option(False, "poses: SIFT with domain-size pooling")
    sfm_guided_matching: bool = option(
        False, "poses: guided matching (re-match with the two-view geometry)"
    )
    sfm_final_ba: bool = option(
        True,
        "poses: a final robust bundle adjustment with tight tolerances after filtering "
        "points with large reprojection error or small triangulation angle",
    )
    seed: int = option(0, "poses: random seed of SfM", low=0)
    turntable: str = option(
        "auto",
        "poses: turntable pose model (one rotation axis, one angle per view, solved from the "
        "silhouettes; seeded by the views SfM registered consistently): on = always; auto = when "
        "SfM registers fewer than --min-registered-fraction of the views or its self-check "
        "fails, and the views look like an ordered turntable sequence; off = SfM only",
        choices=["auto", "on", "off"],
    )
    turntable_step: float | None = option(
        None,
        "poses: degrees the object turns between consecutive views (turntable model; default: "
        "searched around 360 / views)",
        low=-180.0,
        high=180.0,
    )
    turntable_iterations: int = option(300, "poses: refinement steps of the turntable model", low=0)
    min_silhouette_iou: float = option(
        0.8,
        "poses: self-check: least mean IoU of the masks with the silhouettes of the visual hull "
        "(after poses) and of the proxy mesh (report); below it the run stops",
        low=0.0,
        high=1.0,
    )
    max_reprojection_px: float = option(
        2.0,
        "poses: self-check: largest mean SfM reprojection error (pixels at the SfM image size)",
        low=0.0,
    )
    dataset_depth_tolerance: float = option(
        0.025,
        "poses: the capture's depth maps are used with estimated poses only when one scale "
        "takes them to the poses' units within this relative deviation (median over the "
        "sparse points, and each view's median); otherwise they are dropped with a warning "
        "and the depth stage uses the visual hull and stereo",
        low=0.0,
    )
    target_radius: float = option(
        0.85, "normalize: radius of the object's bounding sphere in run units", low=0.01
    )
    depth_method: str = option(
        "auto",
        "depth: dataset = the capture's depth maps; visual_hull; visual_hull+stereo = hull depth "
        "refined by two-view SGBM stereo where consistent (concavities); auto = dataset when "
        "every view has depth, else visual_hull+stereo",
        choices=["auto", "dataset", "visual_hull", "visual_hull+stereo"],
    )
    stereo_max_behind: float = option(
        0.15,
        "depth: stereo may lie at most this far (run units) behind the hull surface",
        low=0.0,
    )
    hull_resolution: int = option(160, "depth: visual-hull voxels along the longest side", low=8)
    hull_tolerance: int = option(
        1, "depth: views allowed to disagree when carving the visual hull", low=0
    )
    min_depth_fraction: float = option(
        0.5,
        "depth: stop when fewer of the masked pixels than this get depth (a partial capture "
        "whose visual hull is open and where stereo finds little)",
        low=0.0,
        high=1.0,
    )
    tsdf_voxel_size: float = option(1 / 256, "proxy: TSDF voxel size in run units", low=1e-5)
    tsdf_trunc_voxels: float = option(3.0, "proxy: TSDF truncation in voxels", low=0.5)
    proxy_close_with_hull: bool = option(
        True,
        "proxy: close what no view sees by fusing the visual hull, ray cast from virtual views "
        "all around, at low weight (watertight proxy where the hull is; where the hull is "
        "open, no view bounds the object and nothing is closed)",
    )
    proxy_carve: bool = option(
        True,
        "proxy: the real views' depth clears the free space in front of their surfaces in "
        "every block of the TSDF, so the hull closing (which spans concavities and rises above "
        "faces seen at grazing angles) survives only where no view sees",
    )
    min_component: float = option(
        0.02,
        "proxy: keep connected parts with at least this fraction of the largest part's triangles",
        low=0.0,
        high=1.0,
    )
    target_triangles: int = option(40_000, "proxy: quadric decimation target triangle count", low=4)
    contact_sheet_columns: int = option(6, "report: thumbnails per row in the contact sheet", low=1)
    accept_poor_poses: bool = option(
        False,
        "report: go on when a self-check finds the poses poor (the verdict in recon_report.json "
        "stays 'poor'; by default the run stops there)",
    )


def proxy_params(cfg: ReconConfig):
    """The proxy_mesh stage's TSDF/cleaning settings (recon.proxy_mesh.ProxyParams)."""
    from recon.proxy_mesh import ProxyParams

    return ProxyParams(
        voxel_size=cfg.tsdf_voxel_size,
        trunc_voxels=cfg.tsdf_trunc_voxels,
        target_triangles=cfg.target_triangles,
        min_component=cfg.min_component,
    )


def stage_options(cfg: ReconConfig, stage: str, ignore_poses: bool = False) -> dict:
    """The options `stage` depends on: the ReconConfig fields whose help starts with
    "<stage>:" (proxy_mesh: "proxy:"), and --ignore-poses for the poses."""
    prefix = _HELP_PREFIX.get(stage, stage) + ":"
    options = {
        f.name: getattr(cfg, f.name)
        for f in dataclasses.fields(cfg)
        if f.metadata.get("help", "").startswith(prefix)
    }
    if stage == "poses":
        options["ignore_poses"] = ignore_poses
    return options


def sfm_too_few(registered: int, total: int, cfg: ReconConfig) -> str:
    return (
        f"structure from motion registered only {registered} of {total} views "
        f"(< {cfg.min_registered_fraction:.0%}). Try: check the masks (masks/ in the run "
        "directory, or give --masks DIR), --turntable on for a turntable capture, capture with "
        "more overlap between neighbouring views (<= 10-15 degrees of turn) and more texture, "
        "or give known poses (transforms.json, COLMAP, ...)"
    )


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


class Pipeline:
    """Runs the stages on one run directory; `state` persists in recon_state.json."""

    def __init__(
        self, run: RunDir, cfg: ReconConfig, force: bool = False, ignore_poses: bool = False
    ):
        self.run, self.cfg, self.force, self.ignore_poses = run, cfg, force, ignore_poses
        self.state_path = run.root / "recon_state.json"
        self.state = read_json(self.state_path) if self.state_path.is_file() else {"stages": {}}
        change = format_change(self.state.get("format_version"), "recon")
        if change is not None and set(self.state["stages"]) - {"ingest"}:
            print(f"[recon] {self.state_path} is out of date ({change}): every stage runs again")
            self.state["stages"] = {k: v for k, v in self.state["stages"].items() if k == "ingest"}
        self.state["format_version"] = FORMAT_VERSIONS["recon"]

    # ---- bookkeeping ------------------------------------------------------------------------
    def _done(self, stage: str) -> bool:
        return bool(self.state["stages"].get(stage, {}).get("done"))

    def _record(self, stage: str, info: dict, seconds: float) -> None:
        later = STAGES[STAGES.index(stage) + 1 :]
        for name in later:
            self.state["stages"].pop(name, None)
        self.state["stages"][stage] = {"done": True, "seconds": round(seconds, 3), **info}
        if stage != "ingest":  # ingest keeps its own options (captures.json)
            options = stage_options(self.cfg, stage, self.ignore_poses)
            self.state.setdefault("options", {})[stage] = options
        write_json(self.state_path, self.state)

    def _changed(self, stage: str) -> list[str]:
        """Options of a finished stage that differ from the ones given now (an option added
        after the stage ran counts as its default)."""
        from recon.training import changed_options

        old = self.state.get("options", {}).get(stage, {})
        new = stage_options(self.cfg, stage, self.ignore_poses)
        defaults = stage_options(ReconConfig(), stage, self.ignore_poses)
        return changed_options({**defaults, **old}, new)

    def run_stage(self, stage: str, fn, *args) -> dict:
        if self._done(stage) and not self.force:
            changes = self._changed(stage)
            if not changes:
                print(f"[recon] {stage}: done already (use --force to redo)")
                return self.state["stages"][stage]
            print(f"[recon] {stage}: options changed ({'; '.join(changes)}): running it again")
        t0 = time.perf_counter()
        if STAGES.index(stage) < STAGES.index("normalize"):
            self.drop_given_inputs()  # new cameras and depth on the way: normalise those
        info = fn(*args) or {}
        self._record(stage, info, time.perf_counter() - t0)
        if stage == "normalize":  # recorded: the inputs it kept aside are no longer needed
            self.drop_given_inputs()
        print(f"[recon] {stage}: {time.perf_counter() - t0:.1f} s")
        return self.state["stages"][stage]

    # ---- helpers ----------------------------------------------------------------------------
    def drop_given_inputs(self) -> None:
        """Removes what an interrupted normalize stage kept of its inputs (see stage_normalize)."""
        (self.run.root / GIVEN_CAMERAS).unlink(missing_ok=True)
        if self.run.depth.is_dir():
            for kept in self.run.depth.glob(f"*{GIVEN_DEPTH}"):
                kept.unlink()

    def views(self) -> list[dict]:
        return [r for r in self.run.load_captures()["images"] if r.get("status", "ok") == "ok"]

    def masks_for(self, cameras) -> list[np.ndarray]:
        return [read_mask(self.run.mask_path(c.name)) for c in cameras]

    # ---- stages -----------------------------------------------------------------------------
    def stage_masks(self) -> dict:
        from recon.masks import MaskParams, compute_masks

        views = self.views()
        redo = set(self.state["stages"].get("masks", {}).get("auto", [])) if self.force else set()
        params = MaskParams(
            border_fraction=self.cfg.mask_border_fraction,
            lightness_weight=self.cfg.mask_lightness_weight,
            grabcut_iterations=self.cfg.mask_grabcut_iterations,
            method=self.cfg.mask_method,
        )
        names = [r["name"] for r in views]
        cameras = None  # the capture's own cameras make saliency masks multi-view consistent
        if self.run.load_captures().get("poses") and self.run.cameras.is_file():
            by_name = {c.name: c for c in self.run.load_cameras().frames}
            if not self.ignore_poses and all(n in by_name for n in names):
                cameras = [by_name[n] for n in names]
        out = compute_masks(
            [self.run.image_path(n) for n in names],
            [self.run.mask_path(n) for n in names],
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

    def thresholds(self):
        from recon.selfcheck import CheckThresholds

        return CheckThresholds(
            min_silhouette_iou=self.cfg.min_silhouette_iou,
            max_reprojection_px=self.cfg.max_reprojection_px,
        )

    def check_poses(self, cams, reprojection_px=None) -> dict:
        """The self-check of poses (recon.selfcheck) as a dict for the stage info."""
        from recon.selfcheck import check_poses

        masks = self.masks_for(cams)
        turntable = self.cfg.turntable == "on"
        verdict = check_poses(cams, masks, self.thresholds(), reprojection_px, turntable=turntable)
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

    def stage_poses(self) -> dict:
        """Poses from the capture, SfM, or the turntable model (module doc of recon.turntable):
        `turntable` on = always; auto = when SfM registers too few views or its self-check
        fails and the views look like an ordered turntable sequence; off = SfM only."""
        captures = self.run.load_captures()
        views = self.views()
        if captures.get("poses") and self.run.cameras.is_file() and not self.ignore_poses:
            cams = self.run.load_cameras()
            return {
                "pose_source": "input",
                "registered_views": len(cams.frames),
                "total_views": len(views),
                "unregistered": [],
                "mean_reprojection_error_px": None,
                "self_check": self.check_poses(cams.frames),
            }
        mode = self.cfg.turntable
        try:
            info, frames, sfm = self.sfm_poses(views, partial=mode != "off")
        except SineError as exc:
            if mode == "off":
                raise
            info, frames, sfm = {"sfm_error": str(exc)}, [], None
        n = len(views)
        enough = bool(frames) and len(frames) >= self.cfg.min_registered_fraction * n
        check = self.check_poses(frames, info["mean_reprojection_error_px"]) if enough else None
        fallback = None
        if mode == "on":
            fallback = "--turntable on"
        elif not enough:
            fallback = f"SfM registered {len(frames)} of {n} views"
        elif check["verdict"] != "ok":
            fallback = "the SfM self-check failed"
        if fallback and mode == "auto":
            from recon.selfcheck import looks_like_turntable

            masks = [read_mask(self.run.mask_path(r["name"])) for r in views]
            if not looks_like_turntable(masks):
                print(f"[recon] poses: {fallback}; the views do not look like a turntable")
                fallback = None
        if fallback is None:
            if not enough:
                raise SineError(info.get("sfm_error") or sfm_too_few(len(frames), n, self.cfg))
            self.use_sfm(views, sfm, frames, info)
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
        turntable = self.turntable_poses(views, sfm)
        return {**turntable, "turntable_reason": fallback, **sfm_info}

    def sfm_params(self, partial: bool):
        from recon.poses import SfmParams

        return SfmParams(
            camera_model=self.cfg.camera_model,
            exhaustive_below=self.cfg.exhaustive_below,
            sequential_overlap=self.cfg.sequential_overlap,
            min_registered_fraction=0.0 if partial else self.cfg.min_registered_fraction,
            mapper=self.cfg.mapper,
            seed=self.cfg.seed,
            peak_threshold=self.cfg.sfm_peak_threshold,
            num_threads=self.cfg.sfm_threads,
            estimate_affine_shape=self.cfg.sfm_affine_shape,
            domain_size_pooling=self.cfg.sfm_domain_size_pooling,
            guided_matching=self.cfg.sfm_guided_matching,
            final_ba=self.cfg.sfm_final_ba,
        )

    def prior_intrinsics(self, views: list[dict]) -> dict[str, Camera]:
        """Intrinsics the capture carries (ingest keeps them per record unless
        --ignore-intrinsics): --ignore-poses drops only the extrinsics."""
        return {
            r["name"]: Camera(width=r["width"], height=r["height"], **r["intrinsics"])
            for r in views
            if r.get("intrinsics")
        }

    def sfm_poses(self, views: list[dict], partial: bool = False):
        """Structure from motion on the views (recon.poses): stage info, the registered cameras
        at the working size and the SfmResult (nothing written yet: see `use_sfm`).
        `partial`: too few registered views is not an error here."""
        from recon.poses import prepare_sfm_images, run_sfm

        work = self.run.root / "sfm"
        sfm_views = []
        for r in views:
            source = Path(r["source"]) if r.get("source") and not r.get("undistorted") else None
            sfm_views.append(
                (r["name"], self.run.image_path(r["name"]), self.run.mask_path(r["name"]), source)
            )
        image_dir, mask_dir = prepare_sfm_images(
            sfm_views,
            work,
            self.cfg.sfm_max_image_size,
            min_object_px=self.cfg.sfm_min_object_px,
            max_upscale=self.cfg.sfm_max_upscale,
        )
        names = [r["name"] for r in views]
        result = run_sfm(
            image_dir,
            mask_dir,
            names,
            work,
            self.sfm_params(partial),
            intrinsics=self.prior_intrinsics(views),
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

    def use_sfm(self, views: list[dict], result, frames: list[Camera], info: dict) -> None:
        """Writes the SfM cameras; dataset depth into SfM units when one scale fits it (else it
        is dropped, `verify_dataset_depth`); undistortion in place."""
        from recon.poses import depth_scale_to_sfm, undistort_depth_in_place, undistort_in_place

        by_name = {r["name"]: r for r in views}
        depth_paths = {
            r["name"]: self.run.depth_path(r["name"])
            for r in views
            if by_name[r["name"]].get("depth")
        }
        if depth_paths:
            fit = depth_scale_to_sfm(
                result.observations,
                depth_paths,
                result.cameras,
                tolerance=self.cfg.dataset_depth_tolerance,
            )
            self.verify_dataset_depth(fit, list(depth_paths.values()), "sfm", info)
        if np.any(result.distortion != 0):
            for c in frames:
                undistort_in_place(
                    [self.run.image_path(c.name)], c, result.distortion, nearest=False
                )
                undistort_in_place([self.run.mask_path(c.name)], c, result.distortion, nearest=True)
                if info.get("dataset_depth_verified") and c.name in depth_paths:
                    undistort_depth_in_place(depth_paths[c.name], c, result.distortion)
            info["undistorted_distortion"] = [float(x) for x in result.distortion]
        self.run.save_cameras(CameraSet(frames=frames, extra={"source_format": "sfm"}))

    def verify_dataset_depth(self, fit, depth_paths: list[Path], poses: str, info: dict) -> None:
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

    def turntable_poses(self, views: list[dict], sfm) -> dict:
        """Every view posed by the turntable model (recon.turntable), seeded by the largest SfM
        model whose views are consistent; writes cameras.json; stage info."""
        from recon.selfcheck import check_poses
        from recon.turntable import TurntableParams, choose_seed, solve_turntable
        from render.device import torch_threads

        names = [r["name"] for r in views]
        by_name = {r["name"]: r for r in views}
        masks = [read_mask(self.run.mask_path(n)) for n in names]
        h, w = masks[0].shape
        prior = self.prior_intrinsics(views)
        seed = choose_seed(sfm.models if sfm else [], names, masks, self.thresholds())
        intrinsics = prior.get(names[0])
        if intrinsics is None and seed is not None:
            intrinsics = seed[0][0]  # SfM's estimate
        params = TurntableParams(
            step_deg=self.cfg.turntable_step, iterations=self.cfg.turntable_iterations
        )
        with torch_threads(self.cfg.sfm_threads):
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
        depth_paths = [self.run.depth_path(n) for n in names if by_name[n].get("depth")]
        if depth_paths:
            fit = self.turntable_depth_scale(frames)
            self.verify_dataset_depth(fit, depth_paths, "turntable", info)
        self.run.save_cameras(CameraSet(frames=frames, extra={"source_format": "turntable"}))
        verdict = check_poses(frames, self.masks_for(frames), self.thresholds(), turntable=True)
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

    def turntable_depth_scale(self, frames: list[Camera]):
        """The factor taking the capture's depth maps into the turntable poses' units
        (`DepthScaleFit`): a first guess from the visual hull's rim, then the ratio at which
        overlapping views' depth maps agree (recon.turntable.consistent_depth_ratios; the rim
        alone came out 3 % low on the toycar, its hull's voxels)."""
        from recon.poses import fit_depth_scale
        from recon.turntable import consistent_depth_ratios, rim_depth_ratios

        masks, depths = [], []
        for cam in frames:
            mask = read_mask(self.run.mask_path(cam.name))
            depth = read_depth(self.run.depth_path(cam.name))
            if depth.shape != mask.shape:
                depth = cv2.resize(depth, mask.shape[::-1], interpolation=cv2.INTER_NEAREST)
            masks.append(mask)
            depths.append(depth)
        tolerance = self.cfg.dataset_depth_tolerance
        rim = fit_depth_scale(rim_depth_ratios(frames, masks, depths), tolerance)
        if rim.factor is None:
            return rim
        fit = fit_depth_scale(consistent_depth_ratios(frames, masks, depths, rim.factor), tolerance)
        return fit if fit.factor is not None else rim

    def stage_normalize(self) -> dict:
        from recon.normalize import apply_normalization, compute_normalization
        from render.cameras import load_cameras, save_cameras

        # the stage rewrites its own inputs: they are kept aside until it is recorded, so an
        # interrupted stage starts again from them (never from its half-written outputs)
        given = self.run.root / GIVEN_CAMERAS
        if not given.is_file():
            save_cameras(given, self.run.load_cameras())
        cams = load_cameras(given)
        norm, stats = compute_normalization(
            cams.frames, self.masks_for(cams.frames), self.cfg.target_radius
        )
        new = apply_normalization(cams, norm)
        for cam in cams.frames:  # depth follows the frame's units
            depth = self.run.depth_path(cam.name)
            kept = depth.with_name(depth.stem + GIVEN_DEPTH)
            if depth.is_file() and not kept.is_file():
                write_depth(kept, read_depth(depth))
            if kept.is_file():
                write_depth(depth, read_depth(kept) * np.float32(norm.scale))
        self.run.save_cameras(new)
        return {
            **stats,
            "normalization_scale": new.scale,
            "normalization_center": [float(x) for x in new.center],
        }

    def _hull(self, cams, masks, fresh: bool = False):
        """The visual hull (recon.depth.HullMesh), cached in visual_hull.npz (the depth stage
        refreshes it)."""
        from recon.depth import read_hull, visual_hull

        path = self.run.root / "visual_hull.npz"
        saved = None if fresh else read_hull(path)
        if saved is not None:
            return saved
        hull = visual_hull(cams, masks, self.cfg.hull_resolution, self.cfg.hull_tolerance)
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

    def stage_depth(self) -> dict:
        from recon.depth import visual_hull_depth

        cams = self.run.load_cameras().frames
        by_name = {r["name"]: r for r in self.views()}
        method = self.cfg.depth_method
        have = all(by_name.get(c.name, {}).get("depth") for c in cams)
        poses = self.state["stages"].get("poses", {})
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
        (self.run.root / "visual_hull.npz").unlink(missing_ok=True)  # cams may have changed
        if method in ("auto", "dataset") and have:
            return {"depth_source": "dataset"}
        masks = self.masks_for(cams)
        hull = self._hull(cams, masks, fresh=True)
        depths, stats = visual_hull_depth(
            cams, masks, self.cfg.hull_resolution, self.cfg.hull_tolerance, hull=hull
        )
        source = "visual_hull"
        if method in ("auto", "visual_hull+stereo"):
            from recon.depth import hull_stereo_depth
            from render.io import read_image

            images = [read_image(self.run.image_path(c.name)) for c in cams]
            depths, more = hull_stereo_depth(
                cams,
                images,
                masks,
                depths,
                front_tol=2.0 * stats["hull_voxel_size"],
                max_behind=self.cfg.stereo_max_behind,
            )
            stats.update(more)
            source = "visual_hull+stereo"
        masked = sum(int(m.sum()) for m in masks)
        covered = sum(int((m & (d > 0)).sum()) for m, d in zip(masks, depths, strict=True))
        stats["depth_pixel_fraction"] = covered / max(masked, 1)
        if stats["depth_pixel_fraction"] < self.cfg.min_depth_fraction:
            raise SineError(partial_capture_message(stats, len(cams), source, self.cfg))
        for cam, depth in zip(cams, depths, strict=True):
            write_depth(self.run.depth_path(cam.name), depth)
        return {"depth_source": source, **stats}

    def stage_proxy_mesh(self) -> dict:
        from recon.proxy_mesh import build_proxy, closing_depths, mesh_stats, write_mesh

        cams = self.run.load_cameras().frames
        depths = [read_depth(self.run.depth_path(c.name)) for c in cams]
        masks = self.masks_for(cams)
        closing = None
        if self.cfg.proxy_close_with_hull:
            hull = self._hull(cams, masks)
            closing = closing_depths(hull.vertices, hull.faces, hull.open_faces)
        params = proxy_params(self.cfg)
        mesh = build_proxy(cams, depths, masks, params, closing=closing, carve=self.cfg.proxy_carve)
        write_mesh(self.run.proxy_mesh, mesh)
        return {**mesh_stats(mesh), "proxy_closed_with_hull": closing is not None}

    def stage_report(self) -> dict:
        from recon.report import write_report

        return write_report(
            self.run,
            self.state,
            self.cfg.contact_sheet_columns,
            self.thresholds(),
            accepted=self.cfg.accept_poor_poses,
        )

    def gate(self, stage: str) -> None:
        """Stops the run (SineError) after a stage whose self-check found it poor, unless
        --accept-poor-poses; recon_report.json then says why (verdict 'poor')."""
        from recon.report import write_partial_report
        from recon.selfcheck import stop_message

        info = self.state["stages"].get(stage, {})
        check = info.get("self_check")
        if not check or check.get("verdict") == "ok":
            return
        if self.cfg.accept_poor_poses:
            print(f"[recon] {stage}: self-check poor, going on (--accept-poor-poses)")
            return
        pose_source = self.state["stages"].get("poses", {}).get("pose_source", "")
        if stage != "report":
            write_partial_report(self.run, self.state)
            # the proxy of earlier poses must not meet these cameras in `sine fit`.
            self.run.proxy_mesh.unlink(missing_ok=True)
        raise SineError(stop_message(stage, check["reasons"], pose_source))


# what the normalize stage keeps of its inputs until it is recorded
GIVEN_CAMERAS, GIVEN_DEPTH = "cameras_given.json", ".given.npy"


def run_recon(capture: Path | None, run: RunDir, cfg: ReconConfig, ingest_cfg=None) -> dict:
    """Runs every stage (skipping finished ones unless ingest_cfg.force or their options
    changed); returns the report."""
    from recon.ingest import IngestConfig
    from render.io import require_directory

    validate(cfg)
    ingest_cfg = validate(ingest_cfg or IngestConfig())
    require_directory(run.root, "--out")
    new_run = not run.root.exists()  # before the lock makes the folder
    with lock_folder(run.root, f"run {run.root}"):
        return _recon(capture, run, cfg, ingest_cfg, new_run)


def _recon(capture: Path | None, run: RunDir, cfg: ReconConfig, ingest_cfg, new_run) -> dict:
    from recon.ingest import ingest_capture, removed_if_refused

    for folder in (run.root, run.images, run.masks, run.depth):  # writes a kill cut short
        remove_partial_writes(folder, recursive=False)
    pipe = Pipeline(run, cfg, force=ingest_cfg.force, ignore_poses=ingest_cfg.ignore_poses)
    if capture is not None:
        t0 = time.perf_counter()
        with removed_if_refused(run.root, new_run):  # later stages' failures keep their run
            summary = ingest_capture(capture, run, ingest_cfg)
        seconds = time.perf_counter() - t0
        if not summary.get("skipped") or not pipe._done("ingest"):
            pipe.drop_given_inputs()
            pipe._record("ingest", {"total_views": summary["views"]}, seconds)
        print(f"[recon] ingest: {'done already' if summary.get('skipped') else f'{seconds:.1f} s'}")
    elif not run.captures.is_file():
        raise SineError(f"{run.root} has no captures.json: give the capture to reconstruct")
    run.append_config("recon", {"recon": to_dict(cfg), "ingest": to_dict(ingest_cfg)})
    # the settings in effect (`sine recon --config` of this file reproduces the run)
    settings = {**to_dict(ingest_cfg), **to_dict(cfg)}
    settings.pop("force")  # what to redo, not how
    write_settings(run.root / "recon_config.toml", settings)
    for stage in STAGES[1:]:
        pipe.run_stage(stage, getattr(pipe, f"stage_{stage}"))
        pipe.gate(stage)
    return read_json(run.recon_report)
