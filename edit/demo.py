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

import argparse
import dataclasses
import html
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from render.configs import add_options, from_args, option, to_dict, validate
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
EDIT_NAME = "geometric"  # RUN/edits/geometric, learnt from the synth's edits/geometric view K
TEXTURE_NAME = "texture"  # RUN/edits/texture, learnt from a recoloured capture of view K
MASKS_EDIT = "demo"  # RUN/edits/demo/semantic_masks (the masks stage)
EDIT_AZIMUTH = 110.0  # degrees: the default view K is the training view nearest this (a side view)

# SfM on a turntable of a symmetric, sparsely textured object: neighbours only (no matches
# between mirror-image views), affine SIFT with domain-size pooling.
RECON = {"exhaustive_below": 0, "sfm_affine_shape": True, "sfm_domain_size_pooling": True}
# Defaults of the full run and of --fast: views, working width, orbit frames, summary rows, and
# the stage options that differ from each command's defaults. The geometric edit mirrors its
# handles across the car's mirror plane (`sine edit --symmetric`): the taller cabin is a
# symmetric edit seen from one side (held-out PSNR +1.0 dB, bench/HISTORY.md "Demo").
FULL = {
    "views": 36,
    "run_width": 256,
    "orbit": 48,
    "rows": 6,
    "recon": {**RECON, "sequential_overlap": 5},
    "fit": {"iterations": 600, "batch_rays": 1024},
    "features": {},
    "edit": {"symmetric": True},
    "texture": {},
}
FAST = {
    "views": 24,
    "run_width": 128,
    "orbit": 24,
    "rows": 5,
    "recon": {
        **RECON,
        "sequential_overlap": 4,
        "tsdf_voxel_size": 1 / 128,
        "target_triangles": 20_000,
    },
    "fit": {"iterations": 300, "batch_rays": 512, "log2_table": 15, "previews": 2},
    "features": {"iterations": 150, "batch_rays": 2048, "log2_table": 13, "previews": 1},
    "edit": {"iterations": 120, "previews": 0, "symmetric": True},
    "texture": {"iterations": 80, "previews": 0},
}


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
    from edit.geometry_edit import GeometryEditConfig
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


# ---- stage bookkeeping (outputs that are not training stages) ------------------------------
class Record:
    """OUT/demo_state.json: the key (options + input files' mtimes) each output stage was made
    with; a stage is skipped when its key is unchanged and its outputs exist."""

    def __init__(self, out: Path, force: bool):
        self.path = out / "demo_state.json"
        self.state = read_json(self.path) if self.path.is_file() and not force else {}

    def done(self, name: str, key: dict, outputs: list[Path]) -> bool:
        return self.state.get(name) == key and all(Path(p).exists() for p in outputs)

    def record(self, name: str, key: dict) -> None:
        self.state[name] = key
        write_json(self.path, self.state)


def mtimes(*paths: Path) -> dict[str, int]:
    return {str(p): p.stat().st_mtime_ns if p.exists() else 0 for p in paths}


class Clock:
    """Seconds per stage. `seconds`: this invocation; `work()`: the seconds of the invocation that
    did each stage's work (a skipped stage keeps the one from the previous demo_summary.json)."""

    def __init__(self, out: Path):
        previous = out / "demo_summary.json"
        self.previous = read_json(previous).get("seconds_work", {}) if previous.is_file() else {}
        self.seconds: dict[str, float] = {}
        self.skipped: set[str] = set()
        self.t0 = time.perf_counter()

    def start(self, name: str) -> None:
        print(f"\n== sine demo: {name} ==", flush=True)
        self.seconds[name] = time.perf_counter()

    def finish(self, name: str, skipped: bool = False) -> None:
        if skipped:
            print(f"{name}: already done with these options")
            self.skipped.add(name)
        self.seconds[name] = round(time.perf_counter() - self.seconds[name], 1)

    def work(self) -> dict[str, float]:
        return {
            k: self.previous.get(k, v) if k in self.skipped else v for k, v in self.seconds.items()
        }


# ---- pictures -----------------------------------------------------------------------------
def resize(image: np.ndarray, width: int, height: int) -> np.ndarray:
    if image.shape[:2] == (height, width):
        return image
    return cv2.resize(image.astype(np.float32), (width, height), interpolation=cv2.INTER_AREA)


def silhouette_iou(opacity: np.ndarray, mask: np.ndarray) -> float:
    a, b = opacity > 0.5, mask > 0.5
    return float((a & b).sum() / max((a | b).sum(), 1))


def object_psnr(pred: np.ndarray, gt: np.ndarray, pred_alpha, gt_mask) -> float:
    from render.metrics import psnr

    sel = (pred_alpha > 0.5) | (gt_mask > 0.5)
    return psnr(pred[sel], gt[sel])


def text_strip(lines: list[str], width: int, scale: float = 0.4) -> np.ndarray:
    """White strip [h, width, 3] with black text lines."""
    step = int(22 * scale + 8)
    strip = np.full((step * len(lines) + 6, width, 3), 255, np.uint8)  # OpenCV draws on 8 bits
    for i, line in enumerate(lines):
        cv2.putText(
            strip, line, (4, step * (i + 1)), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), 1,
            cv2.LINE_AA,
        )  # fmt: skip
    return strip.astype(np.float32) / 255.0


def sheet_rows(frames, k: int, rows: int) -> list[int]:
    """View K first, then every held-out view, then training views spread around the ring."""
    test = [i for i, c in enumerate(frames) if c.split == "test"]
    chosen = [k] + [i for i in test if i != k]
    for i in np.linspace(0, len(frames), 2 * rows, endpoint=False).astype(int):
        if len(chosen) >= rows:
            break
        if all(abs(int(i) - j) > 1 for j in chosen):
            chosen.append(int(i))
    return chosen[:rows]


COLUMNS = ("template", "geometric edit", "its ground truth", "texture edit", "its ground truth")


def compare_views(template, edits: list, frames, rows: list[int], k: int) -> dict:
    """Renders the template and each edit at the views `rows`, next to each edit's GT image.
    edits: [(name, scene, GT folder)]. Returns {"tiles": [row images], "views": [numbers]}."""
    from render.frames import label
    from render.io import read_image

    tiles, numbers = [], []
    gap = np.ones((frames[0].height, 2, 3), np.float32)
    for i in rows:
        cam = frames[i]
        stem = Path(cam.name).stem
        role = "edited view K" if i == k else ("held-out" if cam.split == "test" else "train")
        before = template.render_view(cam)
        b_rgb = np.clip(before["rgb"], 0, 1)
        row = {"view": cam.name, "index": i, "role": role}
        tag = f"{stem} {'K' if i == k else ('held-out' if cam.split == 'test' else 'train')}"
        parts = [label(b_rgb, tag)]
        for name, scene, gt_dir in edits:
            gt = resize(read_image(gt_dir / "images" / f"{stem}.png"), cam.width, cam.height)
            gt_mask = read_mask(gt_dir / "masks" / f"{stem}.png").astype(np.float32)
            gt_mask = resize(gt_mask, cam.width, cam.height)
            after = scene.render_view(cam)
            a_rgb = np.clip(after["rgb"], 0, 1)
            row[f"{name}_silhouette_iou"] = silhouette_iou(after["opacity"], gt_mask)
            row[f"template_silhouette_iou_{name}"] = silhouette_iou(before["opacity"], gt_mask)
            row[f"{name}_psnr_object"] = object_psnr(a_rgb, gt, after["opacity"], gt_mask)
            row[f"template_psnr_object_{name}"] = object_psnr(b_rgb, gt, before["opacity"], gt_mask)
            caption = (
                f"IoU {row[f'{name}_silhouette_iou']:.2f}"
                if name == "geometric"
                else f"{row[f'{name}_psnr_object']:.1f} dB"
            )
            parts += [gap, label(a_rgb, caption), gap, label(gt, "ground truth")]
        numbers.append(row)
        tiles.append(np.concatenate(parts, axis=1))
    return {"tiles": tiles, "views": numbers}


def summary_sheet(tiles: list[np.ndarray], lines: list[str], tile_width: int) -> np.ndarray:
    """Header (column names) + rows of template | each edit | its ground truth + the numbers."""
    width = tiles[0].shape[1]
    header = np.full((20, width, 3), 255, np.uint8)
    for j, name in enumerate(COLUMNS[: (width + 2) // (tile_width + 2)]):
        cv2.putText(
            header, name, (j * (tile_width + 2) + 4, 14), cv2.FONT_HERSHEY_SIMPLEX, 0.4,
            (0, 0, 0), 1, cv2.LINE_AA,
        )  # fmt: skip
    header = header.astype(np.float32) / 255.0
    sep = np.ones((2, width, 3), np.float32)
    body = [x for t in tiles for x in (t, sep)]
    scale = 0.33 if width < 400 else 0.45
    return np.concatenate([header, *body, text_strip(lines, width, scale)], axis=0)


def compare_video(dirs: list[Path], names: list[str], path: Path, fps: float) -> int:
    """Side-by-side video of folders of frames with the same file names (left to right,
    labelled `names`); returns the frame count."""
    from render.frames import strip
    from render.io import read_image
    from render.video import VideoWriter

    frames = sorted(p.name for p in (dirs[0] / "rgb").glob("*.png"))
    with VideoWriter(path, fps) as video:
        for frame in frames:
            video.write(strip([read_image(d / "rgb" / frame) for d in dirs], names))
    return len(frames)


# ---- the demo -----------------------------------------------------------------------------
def has_mirror_plane(run) -> bool:
    """Whether the run's proxy mesh has a clear mirror plane (what `sine edit --symmetric` needs)."""
    from edit.shape_prior import proxy_mirror_plane

    return proxy_mirror_plane(run) is not None


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


def output_stages(cfg: DemoConfig, run, gt_dirs: dict, k: int, record, clock: Clock) -> dict:
    """render / export / view / eval / summary pictures; returns numbers, files, sheet rows.
    gt_dirs: {"geometric": GT of the geometric edit, "texture": GT of the texture edit}."""
    from edit.eval_cli import evaluate_scene
    from edit.export_cli import export_mesh
    from edit.scene import RenderCache, load_scene
    from edit.view_cli import viewer_scene
    from render.camera_paths import orbit_cameras
    from render.frames import render_frames
    from render.viewer import screenshot

    out = cfg.out
    fields = mtimes(
        run.template / "field.pt",
        run.edit(EDIT_NAME) / "edit_field.pt",
        run.edit(TEXTURE_NAME) / "edit_field.pt",
    )
    # the held-out views are scored, then some are shown on the summary sheet: rendered once
    template = RenderCache(load_scene(run.root, None, device=cfg.device))
    edit = RenderCache(load_scene(run.root, EDIT_NAME, device=cfg.device))
    texture = RenderCache(load_scene(run.root, TEXTURE_NAME, device=cfg.device))
    frames = run.load_cameras().frames
    files = {
        "summary_png": "summary.png",
        "summary_html": "summary.html",
        "target": "target.png",
        "target_before_after": "target_before_after.png",
        "texture_target": "texture_target.png",
        "texture_target_before_after": "texture_target_before_after.png",
        "template_video": "template.mp4",
        "edit_video": "edit.mp4",
        "texture_video": "texture.mp4",
        "compare_video": "compare.mp4",
        "template_mesh": "template.glb",
        "edited_mesh": "edited.glb",
        "textured_mesh": "texture_edited.glb",
        "viewer": "viewer.png",
    }

    clock.start("render")
    key = {"orbit": cfg.orbit, "fields": fields, "supersample": cfg.video_supersample}
    videos = {
        name: dataclasses.replace(scene.scene, supersample=cfg.video_supersample)
        for name, scene in (("template", template), ("edit", edit), ("texture", texture))
    }
    paths = [out / files[f"{v}_video"] for v in videos] + [out / files["compare_video"]]
    skip = record.done("render", key, paths)
    if not skip:
        cams = orbit_cameras(frames, cfg.orbit)
        fps = max(8.0, cfg.orbit / 5.0)  # one turn in about 5 s
        for name, scene in videos.items():
            video = out / files[f"{name}_video"]
            render_frames(scene, cams, out / "orbit" / name, video=video, fps=fps)
        names = ["template", "geometric edit", "texture edit"]
        compare_video([out / "orbit" / v for v in videos], names, paths[-1], fps)
        record.record("render", key)
    clock.finish("render", skip)

    clock.start("export")
    key = {"fields": fields}
    meshes = {"template_mesh": template, "edited_mesh": edit, "textured_mesh": texture}
    skip = record.done("export", key, [out / files[f] for f in meshes])
    if not skip:
        for f, scene in meshes.items():
            stats = export_mesh(scene, out / files[f])
            print(f"export: {stats['vertices']} vertices ({scene.name}) -> {out / files[f]}")
        record.record("export", key)
    clock.finish("export", skip)

    clock.start("view")
    key = {"fields": fields}
    skip = record.done("view", key, [out / files["viewer"]])
    if not skip:
        try:
            screenshot(viewer_scene(run.root, EDIT_NAME, device=cfg.device), out / files["viewer"])
            record.record("view", key)
        except SineError as exc:  # no EGL / display: everything else is still worth having
            print(f"view: no screenshot ({exc})")
            files.pop("viewer")
    clock.finish("view", skip)

    clock.start("eval")
    key = {"fields": fields, "gt": {k: str(v) for k, v in gt_dirs.items()}}
    evals = {  # file: (scene, ground truth, edit-region masks)
        "eval_edit.json": (edit, gt_dirs["geometric"], None),
        "eval_template_vs_gt_edit.json": (template, gt_dirs["geometric"], None),
        "eval_texture.json": (texture, gt_dirs["texture"], out / "texture_part"),
        "eval_template_vs_gt_texture.json": (template, gt_dirs["texture"], out / "texture_part"),
    }
    skip = record.done("eval", key, [out / f for f in evals])
    if not skip:
        for f, (scene, gt, regions) in evals.items():
            write_json(out / f, evaluate_scene(scene, gt, regions, split="test"))
        record.record("eval", key)
    clock.finish("eval", skip)
    mean = {f: read_json(out / f)["mean"] for f in evals}

    clock.start("summary")
    rows = sheet_rows(frames, k, (FAST if cfg.fast else FULL)["rows"])
    # what the sheet's pictures and lines come from (the other numbers follow the fields)
    masks = mtimes(run.edit(MASKS_EDIT) / "semantic_masks" / "metrics.json")
    summary_key = {"fields": fields, "masks": masks, "rows": rows, "gt": key["gt"]}
    previous = out / "demo_summary.json"
    skip = record.done("summary", summary_key, [out / files["summary_png"], previous])
    if skip:  # the sheet stays; its numbers are the previous summary's
        views = {"views": read_json(previous)["views_compared"], "tiles": None}
    else:
        edits = [
            ("geometric", edit, gt_dirs["geometric"]),
            ("texture", texture, gt_dirs["texture"]),
        ]
        views = compare_views(template, edits, frames, rows, k)
    held = [v for v in views["views"] if v["role"] == "held-out"]
    edited = views["views"][0]
    geo, geo_t = mean["eval_edit.json"], mean["eval_template_vs_gt_edit.json"]
    tex, tex_t = mean["eval_texture.json"], mean["eval_template_vs_gt_texture.json"]
    numbers = {
        "edit_heldout_psnr": geo.get("psnr"),
        "edit_heldout_psnr_object": geo.get("psnr_object"),
        "edit_heldout_ssim": geo.get("ssim"),
        "template_vs_gt_edit_heldout_psnr": geo_t.get("psnr"),
        "template_vs_gt_edit_heldout_psnr_object": geo_t.get("psnr_object"),
        "edit_heldout_silhouette_iou": float(
            np.mean([v["geometric_silhouette_iou"] for v in held])
        ),
        "template_vs_gt_edit_heldout_silhouette_iou": float(
            np.mean([v["template_silhouette_iou_geometric"] for v in held])
        ),
        "edited_view_silhouette_iou": edited["geometric_silhouette_iou"],
        "edited_view_psnr_object": edited["geometric_psnr_object"],
        "template_vs_gt_edit_edited_view_silhouette_iou": edited[
            "template_silhouette_iou_geometric"
        ],
        "texture_heldout_psnr_object": tex.get("psnr_object"),
        "texture_heldout_psnr_part": tex.get("psnr_region"),
        "texture_heldout_psnr_rest": tex.get("psnr_outside_region"),
        "template_vs_gt_texture_heldout_psnr_object": tex_t.get("psnr_object"),
        "template_vs_gt_texture_heldout_psnr_part": tex_t.get("psnr_region"),
        "template_vs_gt_texture_heldout_psnr_rest": tex_t.get("psnr_outside_region"),
        "texture_edited_view_psnr_object": edited["texture_psnr_object"],
        "views_compared": views["views"],
    }
    clock.finish("summary", skip)
    return {"numbers": numbers, "files": files, "rows": views["tiles"], "summary_key": summary_key}


def summary_lines(s: dict) -> list[str]:
    """The numbers of the summary, one short line each."""
    f = lambda x, d=2: "n/a" if x is None else f"{x:.{d}f}"  # noqa: E731
    return [
        f"{s['object']}, {s['views']} views, {s['registered_views']}/{s['views']} posed "
        f"({s.get('pose_source') or 'n/a'}); "
        f"template held-out PSNR {f(s['template_heldout_psnr'])} dB",
        f"semantic masks ({s['painted_part']}) held-out IoU "
        f"{f(s['semantic_mask_heldout_iou_mean'], 3)}",
        f"edit vs GT, held-out: PSNR {f(s['edit_heldout_psnr'])} dB "
        f"(template {f(s['template_vs_gt_edit_heldout_psnr'])}), sil. IoU "
        f"{f(s['edit_heldout_silhouette_iou'], 3)} "
        f"(template {f(s['template_vs_gt_edit_heldout_silhouette_iou'], 3)})",
        f"edited view {Path(s['edit_view']).stem}: sil. IoU {f(s['edited_view_silhouette_iou'], 3)}"
        f" (template {f(s['template_vs_gt_edit_edited_view_silhouette_iou'], 3)}), object PSNR "
        f"{f(s['edited_view_psnr_object'])} dB",
        f"texture edit ({s['texture_part']} recoloured) vs GT, held-out: object PSNR "
        f"{f(s['texture_heldout_psnr_object'])} dB (template "
        f"{f(s['template_vs_gt_texture_heldout_psnr_object'])})",
        f"  on the {s['texture_part']} {f(s['texture_heldout_psnr_part'])} dB (template "
        f"{f(s['template_vs_gt_texture_heldout_psnr_part'])}), elsewhere "
        f"{f(s['texture_heldout_psnr_rest'])} dB (template "
        f"{f(s['template_vs_gt_texture_heldout_psnr_rest'])})",
    ]


def write_html(out: Path, s: dict, tiles: list[np.ndarray] | None) -> None:
    """OUT/summary.png (unless `tiles` is None: the sheet is unchanged) and OUT/summary.html
    (pictures and videos referenced next to it)."""
    from render.io import write_image, write_text_atomic

    lines = summary_lines(s)
    if tiles is not None:
        write_image(out / "summary.png", summary_sheet(tiles, lines, s["run_size"][0]))
    files = s["files"]
    rel = {
        "recon contact sheet": "run/recon_contact_sheet.png",
        "semantic masks": f"run/edits/{MASKS_EDIT}/semantic_masks/overlay_contact_sheet.png",
        "shape prior": f"run/edits/{EDIT_NAME}/prior_preview.png",
        "edited view: template | edit | target": f"run/edits/{EDIT_NAME}/edited_view.png",
        "texture edit, edited view": f"run/edits/{TEXTURE_NAME}/edited_view.png",
    }
    rows = "".join(
        f"<tr><td>{html.escape(k)}</td><td>{v:.4g}</td></tr>"
        if isinstance(v, float)
        else f"<tr><td>{html.escape(k)}</td><td>{html.escape(str(v))}</td></tr>"
        for k, v in s.items()
        if isinstance(v, (int, float, str)) and k != "config"
    )
    videos = "".join(
        f'<figure><video src="{files[v]}" controls loop autoplay muted></video>'
        f"<figcaption>{v.replace('_', ' ')}</figcaption></figure>"
        for v in ("template_video", "edit_video", "texture_video", "compare_video")
    )
    pictures = "".join(
        f'<figure><img src="{p}"><figcaption>{html.escape(c)}</figcaption></figure>'
        for c, p in [
            ("geometric target (left: the capture of view K, right: the ground-truth edit)",
             files["target_before_after"]),
            ("texture target (left: the capture of view K, right: its part recoloured, as "
             "`sine target --recolor` makes it)", files["texture_target_before_after"]),
            *([("viewer: template | edited mesh", files["viewer"])] if "viewer" in files else []),
            *rel.items(),
        ]
        if (out / p).is_file()
    )  # fmt: skip
    page = f"""<!doctype html>
<html><head><meta charset="utf-8"><title>sine demo</title>
<style>body{{font-family:sans-serif;margin:1em}} img,video{{max-width:100%}}
figure{{display:inline-block;vertical-align:top;margin:0.5em}} td{{padding:0 1em}}</style>
</head><body>
<h1>sine demo: {html.escape(s["object"])}, one geometric and one texture edit</h1>
<p>{"<br>".join(html.escape(x) for x in lines)}</p>
<figure><img src="{files["summary_png"]}"><figcaption>rows: views around the ring (K = the
edited view); columns: template | geometric edit | its ground truth | texture edit | its
ground truth</figcaption></figure>
{videos}
<p>Meshes (capture units, vertex colours): <a href="{files["template_mesh"]}">template</a>,
<a href="{files["edited_mesh"]}">geometric edit</a>,
<a href="{files["textured_mesh"]}">texture edit</a>.
Numbers: <a href="demo_summary.json">demo_summary.json</a>,
<a href="eval_edit.json">eval_edit.json</a>, <a href="eval_texture.json">eval_texture.json</a>.</p>
{pictures}
<table>{rows}</table>
</body></html>
"""
    write_text_atomic(out / "summary.html", page)


DESCRIPTION = __doc__
NAME = "demo"
HELP = "run the whole pipeline on a built-in procedural object, with a geometric and a texture edit"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, DemoConfig, shown=("out", "fast", "procedural", "device", "force"))


def run(args: argparse.Namespace) -> int:
    summary = run_demo(from_args(DemoConfig, args))
    out = Path(args.out)
    print("\n== sine demo: summary ==")
    for line in summary_lines(summary):
        print(f"  {line}")
    print(f"  seconds per stage: {summary['seconds']} (total {summary['seconds_total']})")
    if summary["seconds_work_total"] != summary["seconds_total"]:
        print(f"  (with the skipped stages' own time: {summary['seconds_work_total']} s)")
    print(f"\nLook at: {out / 'summary.png'} (views x template | each edit | its ground truth)")
    print(f"         {out / 'summary.html'} (everything below, with the videos)")
    print(f"         {out / 'compare.mp4'} (orbit: template | geometric edit | texture edit)")
    if "viewer" in summary["files"]:
        print(f"         {out / 'viewer.png'} (template and edited mesh, cameras)")
    print(f"         {out / 'edited.glb'}, {out / 'texture_edited.glb'} (the edited meshes)")
    print(f"         {out / 'run' / 'recon_contact_sheet.png'} (reconstruction)")
    print(f"Numbers: {out / 'demo_summary.json'}")
    return 0
