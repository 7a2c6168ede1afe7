"""The options of `sine recon` (ReconConfig), its stages (STAGES) and the config helpers: the
options each stage depends on (`stage_options`) and the proxy_mesh stage's settings
(`proxy_params`)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from render.configs import option

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
    object_box: list[float] | None = option(
        None,
        "masks: X0 Y0 X1 Y1, a box around the object in view --object-view (pixels of its "
        "original image): for an object in a room, it is segmented there and carried to every "
        "view through the capture's cameras",
    )
    object_view: str = option(
        "0", "masks: the view --object-box is drawn on: its index in the capture or its file name"
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
