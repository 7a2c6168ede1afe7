"""Camera poses by structure from motion (pycolmap), tuned for turntable captures.

A turntable's camera is fixed while the object turns, so matches on the static backdrop say
"nothing moved": SIFT features are extracted inside the foreground masks only (pycolmap's
`mask_path`: a folder of `<image name>.png`, 0 = ignore). Pairs: exhaustive for small sets,
otherwise a cyclic window of neighbours (sequential matching with the loop closed between the
last and first frames). One shared camera (CameraMode.SINGLE), incremental mapping, seeded.

Intrinsics prior: when the capture carries intrinsics (transforms.json, COLMAP, Middlebury...)
and only its poses are ignored, `run_sfm(intrinsics=...)` fixes them (PINHOLE, focal length and
principal point not refined): a narrow-FOV ring around a small object cannot tell focal length
from distance, and a wrong focal length bends the whole ring. Views with different intrinsics
get one camera each.

Small objects: SIFT finds few features when the object covers a small part of the image, so the
SfM images are upsampled until the median foreground bounding-box diagonal reaches
`min_object_px` (at most `max_upscale`, never beyond `max_image_size`).

Final bundle adjustment: after mapping, points with a large reprojection error or a small
triangulation angle are filtered and the model is re-adjusted with a robust (Cauchy) loss and
tight tolerances, twice.
The largest model is kept (all models' cameras come back too: the turntable model takes its
starting values from a consistent one); fewer than `min_registered_fraction` of the views
registered is an error that says what to try. With a distorting camera model the working images and masks are
undistorted in place afterwards (originals kept in sfm/images_distorted) so cameras.json stays
pinhole.
"""

from __future__ import annotations

import shutil
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

from render.cameras import Camera, pose_from_rt
from render.errors import SineError
from render.io import atomic_path, read_depth, read_mask, write_depth, write_mask


@dataclass
class SfmParams:
    """Knobs of the structure-from-motion stage (filled from ReconConfig)."""

    camera_model: str = "SIMPLE_PINHOLE"
    exhaustive_below: int = 60
    sequential_overlap: int = 10
    max_num_features: int = 8192
    max_image_size: int = 1600
    peak_threshold: float = 0.004
    init_min_num_inliers: int = 50
    init_min_tri_angle: float = 8.0
    min_registered_fraction: float = 0.7
    mapper: str = "auto"  # auto: incremental, then global when views are missing
    seed: int = 0
    num_threads: int = -1
    estimate_affine_shape: bool = False
    domain_size_pooling: bool = False
    guided_matching: bool = False
    final_ba: bool = True
    final_ba_max_error_px: float = 2.0
    final_ba_min_tri_angle: float = 1.5


@dataclass
class SfmResult:
    cameras: list[Camera]  # registered views, in input order
    unregistered: list[str]
    mean_reprojection_error_px: float
    points: np.ndarray  # [P, 3] sparse points (SfM frame)
    num_models: int
    distortion: np.ndarray  # [4] OpenCV distortion of the shared camera
    observations: dict  # image name -> (keypoints [M, 2], their 3D points [M, 3])
    mapper: str  # "incremental" or "global": which mapper gave the kept model
    intrinsics: str = "estimated"  # "fixed (prior)" when the capture's intrinsics were used
    # every model the mappers found: (mapper, its registered cameras in input order)
    models: list[tuple[str, list[Camera]]] = field(default_factory=list)


def _write_pairs(path: Path, names: list[str], overlap: int) -> None:
    """A cyclic window: every frame with its `overlap` successors, wrapping around (loop closure)."""
    n = len(names)
    pairs = {
        (min(i, (i + k) % n), max(i, (i + k) % n)) for i in range(n) for k in range(1, overlap + 1)
    }
    path.write_text("".join(f"{names[i]} {names[j]}\n" for i, j in sorted(pairs) if i != j))


def _camera_from_colmap(image, camera) -> tuple[Camera, np.ndarray]:
    """pycolmap image + camera -> our Camera (distortion kept separately) and OpenCV dist [4]."""
    model = camera.model.name
    p = np.asarray(camera.params, dtype=np.float64)
    dist = np.zeros(4)
    if model == "SIMPLE_PINHOLE":
        fx = fy = p[0]
        cx, cy = p[1], p[2]
    elif model == "PINHOLE":
        fx, fy, cx, cy = p
    elif model == "SIMPLE_RADIAL":
        fx = fy = p[0]
        cx, cy, dist[0] = p[1], p[2], p[3]
    elif model == "RADIAL":
        fx = fy = p[0]
        cx, cy, dist[0], dist[1] = p[1], p[2], p[3], p[4]
    else:
        raise SineError(f"unsupported camera model {model}: use PINHOLE, SIMPLE_RADIAL or RADIAL")
    cam_from_world = image.cam_from_world()
    m = np.asarray(cam_from_world.matrix(), dtype=np.float64)  # [3, 4]
    c2w = pose_from_rt(m[:, :3], m[:, 3])  # m = [R | t], world-to-camera
    cam = Camera(
        width=camera.width,
        height=camera.height,
        fx=fx,
        fy=fy,
        cx=cx,
        cy=cy,
        camera_to_world=c2w,
        name=image.name,
    )
    return cam, dist


def foreground_diagonal(masks: list[np.ndarray]) -> float:
    """Median diagonal (pixels) of the masks' foreground bounding boxes (0 when all are empty)."""
    diags = []
    for m in masks:
        rows, cols = np.flatnonzero(m.any(1)), np.flatnonzero(m.any(0))
        if len(rows):
            diags.append(np.hypot(rows[-1] - rows[0] + 1, cols[-1] - cols[0] + 1))
    return float(np.median(diags)) if diags else 0.0


def sfm_upscale(
    object_px: float, width: int, min_object_px: float, max_upscale: float, max_size: int
) -> float:
    """Upsampling factor for SfM images whose object spans `object_px` pixels (1 = none)."""
    if object_px <= 0 or min_object_px <= 0 or object_px >= min_object_px:
        return 1.0
    factor = min(min_object_px / object_px, max_upscale, max_size / width)
    return max(1.0, factor)


def _margin(mask: np.ndarray, width: int, margin: float | None) -> np.ndarray:
    """Grows (margin > 0) or shrinks (< 0) a uint8 mask by `margin` x width/100 pixels;
    None = grow by ~width/200 (features on the outline count)."""
    if margin is None:
        k = max(3, 2 * round(width / 200) + 1)
        return cv2.dilate(mask, np.ones((k, k), np.uint8)) > 0
    r = round(abs(margin) * width / 100)
    if r == 0:
        return mask > 0
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    op = cv2.dilate if margin > 0 else cv2.erode
    return op(mask, kernel) > 0


def prepare_sfm_images(
    views: list[tuple[str, Path, Path, Path | None]],
    work: Path,
    max_size: int,
    min_object_px: float = 0.0,
    max_upscale: float = 2.0,
    mask_margin: float | None = None,
) -> tuple[Path, Path]:
    """Writes SfM inputs: work/images/<name> and work/masks/<name>.png.

    `views` = (name, working image, mask, source image or None). SIFT localises better at the
    source resolution than on the (smaller) working images, so the source is used when it exists
    and has the working image's aspect ratio, downscaled to at most `max_size` pixels wide.
    When the object's median bounding-box diagonal is below `min_object_px` pixels, the images
    are upsampled (bicubic, all by one factor so the camera stays shared; see `sfm_upscale`).
    Masks are resized (nearest) to match and dilated a little (features on the outline count).
    """
    if work.exists():
        shutil.rmtree(work)
    (work / "images").mkdir(parents=True)
    (work / "masks").mkdir()
    sizes = set()
    masks = [read_mask(v[2]) for v in views]
    object_px = foreground_diagonal(masks)
    upscale = None
    for (name, image_path, _, source), mask in zip(views, masks, strict=True):
        working = cv2.imread(str(image_path), cv2.IMREAD_COLOR)
        if working is None:
            raise SineError(f"cannot read {image_path}")
        h, w = working.shape[:2]
        image = working
        if source is not None and Path(source).is_file():
            raw = cv2.imread(str(source), cv2.IMREAD_COLOR)
            if (
                raw is not None
                and abs(raw.shape[1] / raw.shape[0] - w / h) < 1e-3
                and raw.shape[1] > w
            ):
                image = raw
        if image.shape[1] > max(max_size, w):
            s = max(max_size, w) / image.shape[1]
            image = cv2.resize(
                image, (max(max_size, w), round(image.shape[0] * s)), interpolation=cv2.INTER_AREA
            )
        if upscale is None:  # one factor for all views, from the first view's SfM size
            in_sfm_px = object_px * image.shape[1] / w
            upscale = sfm_upscale(
                in_sfm_px, image.shape[1], min_object_px, max_upscale, max(max_size, w)
            )
        if upscale > 1.0:
            size = (round(image.shape[1] * upscale), round(image.shape[0] * upscale))
            image = cv2.resize(image, size, interpolation=cv2.INTER_CUBIC)
        sizes.add(image.shape[:2])
        cv2.imwrite(str(work / "images" / name), image)
        mask = mask.astype(np.uint8)
        mask = cv2.resize(mask, (image.shape[1], image.shape[0]), interpolation=cv2.INTER_NEAREST)
        write_mask(work / "masks" / (name + ".png"), _margin(mask, image.shape[1], mask_margin))
    if len(sizes) > 1:
        raise SineError(
            f"the images have {len(sizes)} different sizes; one shared camera needs one size. "
            "Re-ingest with one --width, or give known poses"
        )
    return work / "images", work / "masks"


def prior_intrinsics(
    image_dir: Path, names: list[str], intrinsics: dict[str, Camera] | None
) -> list[tuple[float, float, float, float]] | None:
    """Per name (fx, fy, cx, cy) scaled to the SfM image sizes, or None without a full prior."""
    if not intrinsics or any(n not in intrinsics for n in names):
        return None
    out = []
    for name in names:
        h, w = cv2.imread(str(image_dir / name), cv2.IMREAD_UNCHANGED).shape[:2]
        cam = intrinsics[name].resized(w, h)
        out.append((cam.fx, cam.fy, cam.cx, cam.cy))
    return out


def _shared(params: list[tuple[float, ...]], rtol: float = 5e-3) -> bool:
    arr = np.asarray(params)
    return bool(np.all(np.abs(arr - arr[0]) <= rtol * np.abs(arr[0]).max()))


def run_sfm(
    image_dir: Path,
    mask_dir: Path,
    names: list[str],
    work: Path,
    params: SfmParams,
    intrinsics: dict[str, Camera] | None = None,
) -> SfmResult:
    """SIFT + matching + mapping on `names` in `image_dir`; masks in `mask_dir`/<name>.png.

    `intrinsics`: known pinhole intrinsics per name (any resolution with the images' aspect
    ratio); when every name has one they are fixed during SfM. Cameras come back at the
    resolution of the images in `image_dir`.
    """
    import pycolmap

    pycolmap.set_random_seed(params.seed)
    db_path = work / "database.db"
    db_path.unlink(missing_ok=True)
    for sub in ("incremental", "global", "sparse"):
        shutil.rmtree(work / sub, ignore_errors=True)
    prior = prior_intrinsics(image_dir, names, intrinsics)
    fixed = prior is not None
    reader = pycolmap.ImageReaderOptions()
    reader.camera_model = "PINHOLE" if fixed else params.camera_model
    reader.mask_path = str(mask_dir)
    camera_mode = pycolmap.CameraMode.SINGLE
    if fixed and _shared(prior):
        reader.camera_params = ",".join(f"{v:.10g}" for v in np.median(prior, axis=0))
    elif fixed:
        camera_mode = pycolmap.CameraMode.PER_IMAGE
    extraction = pycolmap.FeatureExtractionOptions()
    extraction.sift.max_num_features = params.max_num_features
    extraction.sift.peak_threshold = params.peak_threshold
    extraction.sift.estimate_affine_shape = params.estimate_affine_shape
    extraction.sift.domain_size_pooling = params.domain_size_pooling
    extraction.num_threads = params.num_threads
    device = pycolmap.Device.cpu
    pycolmap.extract_features(
        db_path,
        image_dir,
        image_names=names,
        camera_mode=camera_mode,
        reader_options=reader,
        extraction_options=extraction,
        device=device,
    )
    if fixed and camera_mode == pycolmap.CameraMode.PER_IMAGE:
        _write_per_image_intrinsics(db_path, dict(zip(names, prior, strict=True)))
    matching = pycolmap.FeatureMatchingOptions()
    matching.num_threads = params.num_threads
    matching.guided_matching = params.guided_matching
    if len(names) < params.exhaustive_below:
        pycolmap.match_exhaustive(db_path, matching_options=matching, device=device)
    else:
        pairs_path = work / "pairs.txt"
        _write_pairs(pairs_path, names, params.sequential_overlap)
        pairing = pycolmap.ImportedPairingOptions()
        pairing.match_list_path = str(pairs_path)
        pycolmap.match_image_pairs(
            db_path, matching_options=matching, pairing_options=pairing, device=device
        )
    models = {}
    if params.mapper in ("auto", "incremental"):
        options = pycolmap.IncrementalPipelineOptions()
        options.random_seed = params.seed
        options.num_threads = params.num_threads
        options.ba_refine_principal_point = False
        options.ba_refine_focal_length = not fixed
        options.ba_refine_extra_params = not fixed
        # small objects on a turntable give few features and small baselines between neighbours.
        options.mapper.init_min_num_inliers = params.init_min_num_inliers
        options.mapper.init_min_tri_angle = params.init_min_tri_angle
        (work / "incremental").mkdir()
        found = pycolmap.incremental_mapping(
            db_path, image_dir, work / "incremental", options=options
        )
        models.update({("incremental", k): r for k, r in found.items()})
    best_count = max((r.num_reg_images() for r in models.values()), default=0)
    if params.mapper == "global" or (params.mapper == "auto" and best_count < len(names)):
        # Global SfM uses every pair at once: it bridges weak links (wide gaps between views)
        # where incremental mapping splits into several models.
        options = pycolmap.GlobalPipelineOptions()
        options.random_seed = params.seed
        options.num_threads = params.num_threads
        options.mapper.bundle_adjustment.refine_focal_length = not fixed
        options.mapper.bundle_adjustment.refine_principal_point = False
        options.mapper.bundle_adjustment.refine_extra_params = not fixed
        (work / "global").mkdir()
        found = pycolmap.global_mapping(db_path, image_dir, work / "global", options=options)
        models.update({("global", k): r for k, r in found.items()})
    if not any(r.num_reg_images() for r in models.values()):
        raise SineError(
            f"structure from motion registered no views out of {len(names)}. Try: check the masks "
            "(masks/ in the run directory), capture with more overlap between neighbouring views "
            "(<= 10-15 degrees of turn), more texture on the object, or give known poses"
        )
    all_models = [(key[0], _model_cameras(r, names)) for key, r in models.items()]
    # most views registered wins; incremental first on ties (it is listed first).
    best_key = max(models, key=lambda k: models[k].num_reg_images())
    best = models[best_key]
    registered = best.num_reg_images()
    if registered < params.min_registered_fraction * len(names):
        raise SineError(
            f"structure from motion registered only {registered} of {len(names)} views "
            f"(< {params.min_registered_fraction:.0%}). Try: check the masks (masks/ in the run "
            "directory, or give --masks DIR), capture with more overlap between neighbouring views "
            "(<= 10-15 degrees of turn) and more texture, or give known poses (transforms.json, COLMAP, ...)"
        )
    if params.final_ba:
        final_bundle_adjustment(best, params, refine_intrinsics=not fixed)
    (work / "sparse").mkdir()
    best.write(work / "sparse")
    by_name = {}
    for image in best.images.values():
        if image.has_pose:
            by_name[image.name] = _camera_from_colmap(image, best.cameras[image.camera_id])
    cams, dists = [], []
    for name in names:
        if name in by_name:
            cams.append(by_name[name][0])
            dists.append(by_name[name][1])
    points = np.array([p.xyz for p in best.points3D.values()], dtype=np.float64).reshape(-1, 3)
    reproj = float(best.compute_mean_reprojection_error())
    observations = _observations(best)
    distortion = dists[0] if dists else np.zeros(4)
    result = SfmResult(
        cameras=cams,
        unregistered=[n for n in names if n not in by_name],
        mean_reprojection_error_px=reproj,
        points=points,
        num_models=len(models),
        mapper=best_key[0],
        distortion=distortion,
        observations=observations,
        intrinsics="fixed (prior)" if fixed else "estimated",
        models=all_models,
    )
    return result


def _model_cameras(reconstruction, names: list[str]) -> list[Camera]:
    """The registered cameras of one SfM model, in the order of `names`."""
    by_name = {
        image.name: _camera_from_colmap(image, reconstruction.cameras[image.camera_id])[0]
        for image in reconstruction.images.values()
        if image.has_pose
    }
    return [by_name[n] for n in names if n in by_name]


def _write_per_image_intrinsics(db_path: Path, prior: dict[str, tuple]) -> None:
    """Sets each image's own PINHOLE camera in the database to its known intrinsics."""
    import pycolmap

    db = pycolmap.Database.open(db_path)
    try:
        for image in db.read_all_images():
            camera = db.read_camera(image.camera_id)
            camera.params = np.asarray(prior[image.name], np.float64)
            camera.has_prior_focal_length = True
            db.update_camera(camera)
    finally:
        db.close()


def final_bundle_adjustment(reconstruction, params: SfmParams, refine_intrinsics: bool) -> None:
    """Filters poorly constrained points, then a robust, tightly converged global BA (twice)."""
    import pycolmap

    for _ in range(2):
        pycolmap.ObservationManager(reconstruction).filter_all_points3D(
            params.final_ba_max_error_px, params.final_ba_min_tri_angle
        )
        options = pycolmap.BundleAdjustmentOptions()
        options.refine_focal_length = refine_intrinsics
        options.refine_principal_point = False
        options.refine_extra_params = refine_intrinsics
        options.print_summary = False
        options.ceres.loss_function_type = pycolmap.LossFunctionType.CAUCHY
        options.ceres.loss_function_scale = 1.0
        solver = options.ceres.solver_options
        solver.max_num_iterations = 300
        solver.function_tolerance = 1e-12
        solver.gradient_tolerance = 1e-12
        solver.parameter_tolerance = 1e-12
        solver.num_threads = params.num_threads
        pycolmap.bundle_adjustment(reconstruction, options)


def _observations(reconstruction) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per image name: 2D keypoints [M, 2] with a 3D point and those points [M, 3]."""
    out = {}
    for image in reconstruction.images.values():
        if not image.has_pose:
            continue
        uv, xyz = [], []
        for p2d in image.points2D:
            if p2d.has_point3D():
                uv.append(p2d.xy)
                xyz.append(reconstruction.points3D[p2d.point3D_id].xyz)
        out[image.name] = (np.array(uv).reshape(-1, 2), np.array(xyz).reshape(-1, 3))
    return out


def _undistort_maps(camera: Camera, dist: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    K = camera.K.copy()
    K[0, 2] -= 0.5  # OpenCV puts pixel centres at integers
    K[1, 2] -= 0.5
    return cv2.initUndistortRectifyMap(
        K, np.asarray(dist, np.float64), None, K, (camera.width, camera.height), cv2.CV_32FC1
    )


def undistort_depth_in_place(path: Path, camera: Camera, dist: np.ndarray) -> None:
    """Undistorts a stored depth map like `undistort_in_place` (nearest; 0 where no source)."""
    depth = read_depth(path)
    if depth.shape != (camera.height, camera.width):
        camera = camera.resized(depth.shape[1], depth.shape[0])
    map1, map2 = _undistort_maps(camera, dist)
    write_depth(path, cv2.remap(depth, map1, map2, cv2.INTER_NEAREST, borderValue=0.0))


def undistort_in_place(paths: list[Path], camera: Camera, dist: np.ndarray, nearest: bool) -> None:
    """Undistorts images/masks with the pinhole K of `camera` kept (pixel centres at +0.5).

    Images are resampled with Lanczos (8 x 8 taps): bilinear interpolation at the sub-pixel
    shifts of a mild distortion softens the photos (the oxford-dinosaur's texture lost 23 % of
    its Laplacian energy, Lanczos 2.5 %), and the template learns from, and is scored against,
    the softened photos."""
    map1, map2 = _undistort_maps(camera, dist)
    interp = cv2.INTER_NEAREST if nearest else cv2.INTER_LANCZOS4
    for path in paths:
        raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        out = cv2.remap(raw, map1, map2, interp, borderMode=cv2.BORDER_REPLICATE)
        with atomic_path(path) as tmp:
            ok = cv2.imwrite(str(tmp), out)
            if not ok:
                raise SineError(f"could not write {path}")


@dataclass
class DepthScaleFit:
    """One factor taking the capture's depth maps into the poses' units, and how well it fits.

    ratio = pose camera z / dataset depth at a point; `residual` = median |ratio / factor - 1|
    over all points; a view's offset = |its median ratio / factor - 1| (views with at least
    `min_view_points` points). Depth from another camera model, inverse depth, a scale per view
    or garbage gives a large residual or a large worst offset.
    """

    factor: float | None  # median ratio (None: fewer than 10 points)
    points: int
    residual: float  # median relative deviation from the factor
    within: float  # fraction of points within `tolerance` of the factor
    tolerance: float
    worst_view: str | None  # the view whose median ratio is furthest from the factor
    worst_view_offset: float

    def consistent(self) -> bool:
        """The factor fits every view within `tolerance`."""
        return (
            self.factor is not None
            and self.residual <= self.tolerance
            and self.worst_view_offset <= self.tolerance
        )

    def summary(self) -> str:
        if self.factor is None:
            return f"{self.points} sparse points with depth (< 10)"
        return (
            f"scale {self.factor:.4g} from {self.points} points: median deviation "
            f"{self.residual:.1%}, {self.within:.0%} of the points within {self.tolerance:.1%}, "
            f"worst view {self.worst_view} off by {self.worst_view_offset:.1%}"
        )

    def to_dict(self) -> dict:
        """The stage-info keys (recon_report.json); no number when there was no fit."""
        fitted = self.factor is not None
        return {
            "dataset_depth_verified": self.consistent(),
            "dataset_depth_check": self.summary(),
            "dataset_depth_scale_points": self.points,
            "dataset_depth_scale_residual": round(self.residual, 5) if fitted else None,
            "dataset_depth_within_tolerance": round(self.within, 4),
            "dataset_depth_tolerance": self.tolerance,
            "dataset_depth_worst_view": self.worst_view,
            "dataset_depth_worst_view_offset": round(self.worst_view_offset, 5) if fitted else None,
        }


def fit_depth_scale(
    ratios: dict[str, np.ndarray], tolerance: float = 0.05, min_view_points: int = 5
) -> DepthScaleFit:
    """`DepthScaleFit` of per-view ratios [M_i] (pose z / dataset depth, all > 0)."""
    ratios = {k: np.asarray(v, np.float64) for k, v in ratios.items() if len(v)}
    flat = np.concatenate(list(ratios.values())) if ratios else np.zeros(0)
    if len(flat) < 10:
        return DepthScaleFit(None, len(flat), np.inf, 0.0, tolerance, None, np.inf)
    factor = float(np.median(flat))
    dev = np.abs(flat / factor - 1.0)
    offsets = {
        k: abs(float(np.median(v)) / factor - 1.0)
        for k, v in ratios.items()
        if len(v) >= min_view_points
    }
    worst = max(offsets, key=offsets.get) if offsets else None
    return DepthScaleFit(
        factor=factor,
        points=len(flat),
        residual=float(np.median(dev)),
        within=float(np.mean(dev <= tolerance)),
        tolerance=tolerance,
        worst_view=worst,
        worst_view_offset=offsets[worst] if worst else 0.0,
    )


def depth_scale_to_sfm(
    observations: dict,
    depth_paths: dict[str, Path],
    cameras: list[Camera],
    tolerance: float = 0.05,
) -> DepthScaleFit:
    """The factor SfM-z / dataset-depth at the sparse keypoints (`fit_depth_scale`): puts
    dataset depth in SfM units, with how consistently it does so."""
    ratios = {}
    for cam in cameras:
        path = depth_paths.get(cam.name)
        if path is None or not path.is_file() or cam.name not in observations:
            continue
        uv, xyz = observations[cam.name]
        if len(uv) == 0:
            continue
        depth = read_depth(path)
        sy, sx = depth.shape[0] / cam.height, depth.shape[1] / cam.width
        cols = np.clip((uv[:, 0] * sx).astype(int), 0, depth.shape[1] - 1)
        rows = np.clip((uv[:, 1] * sy).astype(int), 0, depth.shape[0] - 1)
        d = depth[rows, cols]
        _, z = cam.project(xyz)
        ok = (d > 0) & (z > 0) & np.isfinite(d)
        ratios[cam.name] = z[ok] / d[ok]
    return fit_depth_scale(ratios, tolerance)


def rescale_depth(paths: list[Path], factor: float) -> None:
    """Multiplies stored depth maps by `factor` (0 stays 0)."""
    for path in paths:
        if path.is_file():
            write_depth(path, read_depth(path) * np.float32(factor))
