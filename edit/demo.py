"""`sine demo`: the main job end to end on a built-in procedural object, with no outside data.

A synthetic turntable with ground truth (`sine synth`), reconstructed from its images alone
(`sine recon`, SfM poses), the template (`sine fit`), the DINO feature field and semantic masks
(`sine features`, `sine masks`), a geometric and a texture edit each learnt from one target image
(`sine target`, `sine edit`), then orbit videos, coloured GLB meshes, a viewer screenshot and
held-out scores against the ground-truth edits (`sine render`, `export`, `view`, `eval`). Each
stage skips finished work. Everything lands under OUT/; look at OUT/summary.png and
OUT/summary.html. `--fast` renders fewer views at a lower working resolution and trains fewer
steps.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from edit.demo_stages import (
    EDIT_NAME,
    FAST,
    FULL,
    MASKS_EDIT,
    TEXTURE_NAME,
    Clock,
    Record,
    has_mirror_plane,
    mtimes,
)
from edit.demo_summary import output_stages, resize, write_html
from render.configs import option, to_dict, validate
from render.errors import SineError
from render.io import read_json, read_label_map, read_mask, require_directory, write_json

# The part painted by default: the one the object's ground-truth geometric edit stretches.
DEFAULT_PART = {"toycar": "cabin", "figurine": "head"}
# Objects the demo poses from their images (SfM, or the turntable model from the silhouettes).
# The figurine is not one: a body of revolution whose stripes are rings around its axis, so its
# silhouettes and three in four of its SIFT matches are the same after any turn (SfM's models
# are degenerate, the turntable model cannot fix the angles, the camera's elevation nor the
# focal length: bench/HISTORY.md "Self-checks and the turntable pose model"); its demo keeps
# the capture's poses and intrinsics.
POSED_FROM_IMAGES = ("toycar",)
EDIT_AZIMUTH = 110.0  # degrees: the default view K is the training view nearest this (a side view)


@dataclass
class DemoConfig:
    """Options of `sine demo`."""

    out: Path = option(Path("runs/demo"), "output folder (summary.html/png, capture/, run/, ...)")
    fast: bool = option(
        False, "fewer views, a lower working resolution and fewer steps (minutes; for tests)"
    )
    procedural: str = option(
        "toycar",
        "built-in object to use; the figurine is a body of revolution with ring stripes, whose "
        "turns no method recovers from its images (silhouettes and stripes look the same from "
        "every side), so its demo keeps the capture's poses",
        choices=["toycar", "figurine"],
    )
    views: int | None = option(None, "turntable views to render (default 36; --fast 24)", low=3)
    width: int = option(256, "synthetic image width in pixels (SfM runs on these)", low=16)
    height: int = option(256, "synthetic image height in pixels", low=16)
    run_width: int | None = option(
        None, "working image width of the run (default 256; --fast 128)", low=16
    )
    paint_part: str = option(
        "auto",
        "part painted in the editing view; auto = the part the GT geometric edit stretches "
        "(toycar: cabin, figurine: head)",
    )
    edit_view: int | None = option(
        None,
        "index K of the edited view (synthetic image r_K), below --views; default: the "
        f"training view nearest {EDIT_AZIMUTH:.0f} degrees azimuth (a side view)",
        low=0,
    )
    orbit: int | None = option(None, "frames of the orbit videos (default 48; --fast 24)", low=1)
    video_supersample: int = option(
        1,
        "rays per pixel side of the orbit videos (1: fast; the stills and metrics use the "
        "template's `sine fit --supersample`)",
        low=1,
    )
    device: str = option("auto", "torch device: auto, cpu or cuda", choices=["auto", "cpu", "cuda"])
    force: bool = option(False, "redo every stage instead of resuming finished ones")


# ---- options ------------------------------------------------------------------------------
def default_edit_view(views: int) -> int:
    """The training view (not every 8th) of the synth ring nearest EDIT_AZIMUTH degrees."""
    from recon.ingest import assign_splits

    splits = assign_splits(views, 8)
    gap = [abs((360.0 * i / views - EDIT_AZIMUTH + 180.0) % 360.0 - 180.0) for i in range(views)]
    return min((i for i in range(views) if splits[i] == "train"), key=lambda i: gap[i])


def resolved(cfg: DemoConfig) -> DemoConfig:
    """`cfg` with every default that depends on --fast filled in."""
    base = FAST if cfg.fast else FULL
    return dataclasses.replace(
        cfg,
        views=cfg.views if cfg.views is not None else base["views"],
        run_width=cfg.run_width if cfg.run_width is not None else base["run_width"],
        orbit=cfg.orbit if cfg.orbit is not None else base["orbit"],
    )


def check_options(cfg: DemoConfig) -> str:
    """Every option error before any work (a SineError); returns the part to paint."""
    from recon.procedural import build

    validate(cfg)
    require_directory(cfg.out, "--out")
    views = cfg.views if cfg.views is not None else (FAST if cfg.fast else FULL)["views"]
    if cfg.edit_view is not None and cfg.edit_view >= views:
        raise SineError(
            f"--edit-view {cfg.edit_view} is out of range: the demo renders {views} views "
            f"(0 to {views - 1})"
        )
    part = DEFAULT_PART[cfg.procedural] if cfg.paint_part == "auto" else cfg.paint_part
    parts = sorted(build(cfg.procedural).mesh.part_names.values())
    if part not in parts:
        raise SineError(
            f"--paint-part {part!r} is not a part of the {cfg.procedural}: {', '.join(parts)}"
        )
    return part


def stage_configs(cfg: DemoConfig) -> dict:
    """The options of every library stage, checked (cfg resolved)."""
    from edit.feature_field_fit import FeaturesConfig
    from edit.geometry_config import GeometryEditConfig
    from edit.part_masks import MasksConfig
    from edit.texture_config import TextureEditConfig
    from recon.fit_config import FitConfig
    from recon.ingest import IngestConfig
    from recon.recon_config import ReconConfig
    from recon.synth import SynthConfig

    base = FAST if cfg.fast else FULL
    dev = {"device": cfg.device}
    configs = {
        "synth": SynthConfig(
            out=cfg.out / "capture",
            procedural=cfg.procedural,
            views=cfg.views,
            width=cfg.width,
            height=cfg.height,
            edit=["geometric", "texture"],
        ),
        "recon": ReconConfig(**base["recon"]),
        "ingest": IngestConfig(
            width=cfg.run_width, ignore_poses=cfg.procedural in POSED_FROM_IMAGES
        ),
        "fit": FitConfig(**dev, **base["fit"]),
        "features": FeaturesConfig(**dev, **base["features"]),
        "masks": MasksConfig(**dev),
        "edit": GeometryEditConfig(**dev, **base["edit"]),
        "texture": TextureEditConfig(**dev, **base["texture"]),
    }
    for name in ("recon", "ingest", "fit", "features", "masks", "edit", "texture"):
        validate(configs[name])  # synthesize() checks its own options
    return configs


# ---- the demo -----------------------------------------------------------------------------
def run_demo(cfg: DemoConfig) -> dict:
    from edit.feature_field_fit import distill_features
    from edit.geometry_edit import run_geometry_edit
    from edit.part_masks import semantic_masks
    from edit.targets import before_after, recolor_region, write_rgba
    from edit.texture_edit import run_texture_edit
    from recon.fit import fit_template
    from recon.pipeline import run_recon
    from recon.rundir import RunDir
    from recon.synth import synthesize
    from render.io import read_image, write_image, write_mask
    from render.metrics import mask_iou

    paint_part = check_options(cfg)
    cfg = resolved(cfg)
    configs = stage_configs(cfg)
    out = cfg.out
    capture, run = out / "capture", RunDir(out / "run")
    gt_dir, tex_gt_dir = capture / "edits" / "geometric", capture / "edits" / "texture"
    k = cfg.edit_view if cfg.edit_view is not None else default_edit_view(cfg.views)
    k_name = f"r_{k:03d}.png"
    clock = Clock(out)
    clock.start("synth")
    synth_cfg = configs["synth"]
    recorded = capture / "synth.json"
    same = recorded.is_file() and read_json(recorded).get("config") == to_dict(synth_cfg)
    force = cfg.force or not same  # a new capture: every later stage is redone
    if force:
        synthesize(synth_cfg)
    labels_dir = capture / "labels"
    part_id = {n: int(v) for v, n in read_json(capture / "parts.json").items()}[paint_part]
    if not (read_label_map(labels_dir / k_name) == part_id).any():
        raise SineError(f"the {paint_part} is not visible in view {k}: choose another --edit-view")
    clock.finish("synth", not force)
    record = Record(out, force)  # what the stages that are not training stages were made from

    clock.start("recon")
    inputs = (run.cameras, run.proxy_mesh)
    before = mtimes(*inputs)
    ingest_cfg = dataclasses.replace(configs["ingest"], force=force)
    report = run_recon(capture, run, configs["recon"], ingest_cfg)
    unchanged = mtimes(*inputs) == before
    force = force or not unchanged  # new poses or proxy: retrain what follows
    clock.finish("recon", unchanged)
    frames = run.load_cameras().frames
    names = [c.name for c in frames]
    if k_name not in names:
        raise SineError(f"view {k_name} was not registered by SfM: choose another --edit-view")
    k_run = names.index(k_name)  # view K's index among the run's cameras

    clock.start("fit")
    template_metrics = fit_template(run.root, configs["fit"], force=force)
    force = force or not template_metrics.get("skipped")
    clock.finish("fit", bool(template_metrics.get("skipped")))

    clock.start("features")
    features = distill_features(run.root, configs["features"], force=force)
    clock.finish("features", bool(features.get("skipped")))

    clock.start("masks")
    edit_cam = frames[k_run]

    def labels_of(name: str, like) -> np.ndarray:  # GT labels at the run's image size
        lab = read_label_map(labels_dir / name)
        if lab.shape == like:
            return lab
        small = cv2.resize(lab.astype(np.uint16), like[::-1], interpolation=cv2.INTER_NEAREST)
        return small.astype(np.int32)

    size = (edit_cam.height, edit_cam.width)
    region = labels_of(edit_cam.name, size) == part_id
    masks_dir = run.edit(MASKS_EDIT) / "semantic_masks"
    key = {"view": k_name, "part": paint_part, "fields": mtimes(run.features / "field.pt")}
    skip = record.done("masks", key, [masks_dir / "metrics.json"])
    if not skip:
        semantic_masks(run.root, k_run, region, masks_dir, configs["masks"])
        record.record("masks", key)
    ious = {
        c.name: mask_iou(
            read_mask(masks_dir / "masks" / (Path(c.name).stem + ".png")),
            labels_of(c.name, size) == part_id,
        )
        for c in frames
        if c.split == "test"
    }
    clock.finish("masks", skip)

    clock.start("target")
    gt_rgb = resize(read_image(gt_dir / "images" / k_name), edit_cam.width, edit_cam.height)
    gt_alpha = resize(read_mask(gt_dir / "masks" / k_name).astype(np.float32), *size[::-1])
    background = synth_cfg.background
    target = out / "target.png"
    write_rgba(target, gt_rgb, gt_alpha, background)
    before_k = resize(read_image(run.image_path(k_name)), edit_cam.width, edit_cam.height)
    write_image(out / "target_before_after.png", before_after(before_k, gt_rgb))
    clock.finish("target")

    clock.start("edit")
    edit_cfg = configs["edit"]
    if edit_cfg.symmetric and not has_mirror_plane(run):
        print("edit: the proxy has no clear mirror plane: the edit is learnt without --symmetric")
        edit_cfg = dataclasses.replace(edit_cfg, symmetric=False)
    edit_metrics = run_geometry_edit(run.root, k_run, target, EDIT_NAME, edit_cfg, force=force)
    clock.finish("edit", bool(edit_metrics.get("skipped")))

    clock.start("texture target")
    recolor = read_json(tex_gt_dir / "edit.json")  # which part the GT recolours, by what hue
    tex_part = int(recolor["part"])
    run_mask_k = resize(read_mask(run.mask_path(k_name)).astype(np.float32), *size[::-1])
    tex_region = (labels_of(k_name, size) == tex_part) & (run_mask_k > 0.5)
    if not tex_region.any():
        raise SineError(
            f"the recoloured part is not visible in view {k}: choose another --edit-view"
        )
    tex_rgb = recolor_region(before_k, tex_region, float(recolor["hue_shift_deg"]))
    tex_target, tex_region_png = out / "texture_target.png", out / "texture_region.png"
    write_rgba(tex_target, tex_rgb, run_mask_k, background)
    write_mask(tex_region_png, tex_region)
    write_image(out / "texture_target_before_after.png", before_after(before_k, tex_rgb))
    for c in frames:  # the part in every view (GT labels at the capture's size): `sine eval`'s
        part = read_label_map(labels_dir / c.name) == tex_part  # inside / outside the region
        write_mask(out / "texture_part" / (Path(c.name).stem + ".png"), part)
    clock.finish("texture target")

    clock.start("texture")
    texture_metrics = run_texture_edit(
        run.root, k_run, tex_target, TEXTURE_NAME, configs["texture"], tex_region_png, force=force
    )
    clock.finish("texture", bool(texture_metrics.get("skipped")))

    outputs = output_stages(
        cfg, run, {"geometric": gt_dir, "texture": tex_gt_dir}, k_run, record, clock
    )

    summary = {
        "object": cfg.procedural,
        "fast": cfg.fast,
        "views": cfg.views,
        "synth_size": [cfg.width, cfg.height],
        "run_size": [edit_cam.width, edit_cam.height],
        "registered_views": report.get("registered_views"),
        "pose_source": report.get("pose_source"),
        "proxy_triangles": report.get("proxy_triangles"),
        "silhouette_iou_mean": report.get("silhouette_iou_mean"),
        "template_heldout_psnr": template_metrics.get("heldout_psnr"),
        "template_heldout_ssim": template_metrics.get("heldout_ssim"),
        "features_heldout_cosine": features.get("heldout_cosine"),
        "painted_part": paint_part,
        "semantic_mask_heldout_iou_mean": float(np.mean(list(ious.values()))),
        "semantic_mask_heldout_iou": ious,
        "edit_view": k_name,
        "edit_view_index": k_run,
        "edit_method": edit_metrics.get("method"),
        "edit_iterations": edit_metrics.get("iterations"),
        **outputs["numbers"],
        "edit_training_metrics": {
            key: edit_metrics.get(key)
            for key in ("edited_view_psnr_object", "edited_view_silhouette_iou", "train_seconds")
        },
        "texture_part": read_json(capture / "parts.json").get(str(tex_part)),
        "texture_iterations": texture_metrics.get("iterations"),
        "files": outputs["files"],
        "seconds": clock.seconds,
        "seconds_work": clock.work(),
        "config": to_dict(cfg),
    }
    summary["seconds_total"] = round(time.perf_counter() - clock.t0, 1)
    summary["seconds_work_total"] = round(sum(summary["seconds_work"].values()), 1)
    write_json(out / "demo_summary.json", summary)
    write_html(out, summary, outputs["rows"])
    record.record("summary", outputs["summary_key"])  # once summary.png matches the key
    return summary
