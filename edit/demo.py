"""`sine demo`: the whole pipeline, as far as it is built, on the built-in procedural toy car.

Stages (each one the library function behind its own command, each skipped when already done):
synth (ground-truth turntable + GT edits) -> recon (known poses) -> fit (template field) ->
features (DINO feature field) -> masks (semantic masks of one painted part, scored against the
ground-truth part labels). Everything lands under OUT/; OUT/demo_summary.json has the numbers.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from render.configs import add_options, from_args, option, to_dict, validate
from render.errors import SineError
from render.io import read_json, read_label_map, read_mask, require_directory, write_json

# The part painted by default: the one the object's ground-truth geometric edit stretches.
DEFAULT_PART = {"toycar": "cabin", "figurine": "head"}


@dataclass
class DemoConfig:
    """Options of `sine demo`."""

    out: Path = option(Path("runs/demo"), "output folder (capture/, run/, demo_summary.json)")
    procedural: str = option("toycar", "built-in object to use", choices=["toycar", "figurine"])
    views: int = option(36, "turntable views to render", low=3)
    width: int = option(256, "image width in pixels", low=16)
    height: int = option(256, "image height in pixels", low=16)
    paint_part: str = option(
        "auto",
        "part painted in the editing view; auto = the part the GT geometric edit stretches "
        "(toycar: cabin, figurine: head)",
    )
    edit_view: int = option(
        11, "index of the editing view (the one the user would paint), below --views", low=0
    )
    device: str = option("auto", "torch device: auto, cpu or cuda", choices=["auto", "cpu", "cuda"])
    force: bool = option(False, "redo every stage instead of resuming finished ones")


def check_options(cfg: DemoConfig) -> str:
    """Every option error before any work (a SineError); returns the part to paint."""
    from recon.procedural import build

    validate(cfg)
    require_directory(cfg.out, "--out")
    if cfg.edit_view >= cfg.views:
        raise SineError(
            f"--edit-view {cfg.edit_view} is out of range: the demo renders {cfg.views} views "
            f"(0 to {cfg.views - 1})"
        )
    part = DEFAULT_PART[cfg.procedural] if cfg.paint_part == "auto" else cfg.paint_part
    parts = sorted(build(cfg.procedural).mesh.part_names.values())
    if part not in parts:
        raise SineError(
            f"--paint-part {part!r} is not a part of the {cfg.procedural}: {', '.join(parts)}"
        )
    return part


def run_demo(cfg: DemoConfig) -> dict:
    from edit.feature_field_fit import FeaturesConfig, distill_features
    from edit.part_masks import MasksConfig, semantic_masks
    from recon.fit import FitConfig, fit_template
    from recon.ingest import IngestConfig
    from recon.pipeline import ReconConfig, run_recon
    from recon.report import mask_iou
    from recon.rundir import RunDir
    from recon.synth import SynthConfig, synthesize

    paint_part = check_options(cfg)
    capture, run = cfg.out / "capture", RunDir(cfg.out / "run")
    seconds: dict[str, float] = {}

    def stage(name: str):
        print(f"\n== sine demo: {name} ==", flush=True)
        seconds[name] = time.perf_counter()

    def done(name: str, result: dict) -> None:
        if result.get("skipped"):
            print(f"{name}: already done with these options")
        seconds[name] = time.perf_counter() - seconds[name]

    stage("synth")
    synth_cfg = SynthConfig(
        out=capture,
        procedural=cfg.procedural,
        views=cfg.views,
        width=cfg.width,
        height=cfg.height,
        edit=["geometric", "texture"],
    )
    recorded = capture / "synth.json"
    same = recorded.is_file() and read_json(recorded).get("config") == to_dict(synth_cfg)
    force = cfg.force or not same  # a new capture: every later stage is redone
    if force:
        synthesize(synth_cfg)
    labels_dir = capture / "labels"
    part_id = {n: int(k) for k, n in read_json(capture / "parts.json").items()}[paint_part]
    names = sorted(p.name for p in labels_dir.glob("*.png"))
    if not (read_label_map(labels_dir / names[cfg.edit_view]) == part_id).any():
        raise SineError(
            f"the {paint_part} is not visible in view {cfg.edit_view}: choose another --edit-view"
        )
    done("synth", {"skipped": not force})

    stage("recon")
    report = run_recon(capture, run, ReconConfig(), IngestConfig(force=force))
    done("recon", {})

    stage("fit")
    template = fit_template(run.root, FitConfig(device=cfg.device), force=force)
    done("fit", template)

    stage("features")
    features = distill_features(run.root, FeaturesConfig(device=cfg.device), force=force)
    done("features", features)

    stage("masks")
    cameras = run.load_cameras().frames
    edit_cam = cameras[cfg.edit_view]
    labels = {c.name: read_label_map(labels_dir / c.name) for c in cameras}
    region = labels[edit_cam.name] == part_id
    masks_dir = run.edit("demo") / "semantic_masks"
    semantic_masks(run.root, cfg.edit_view, region, masks_dir, MasksConfig(device=cfg.device))
    ious = {
        c.name: mask_iou(
            read_mask(masks_dir / "masks" / (Path(c.name).stem + ".png")), labels[c.name] == part_id
        )
        for c in cameras
        if c.split == "test"
    }
    seconds["masks"] = time.perf_counter() - seconds["masks"]

    summary = {
        "object": cfg.procedural,
        "views": cfg.views,
        "registered_views": report.get("registered_views"),
        "proxy_triangles": report.get("proxy_triangles"),
        "silhouette_iou_mean": report.get("silhouette_iou_mean"),
        "template_heldout_psnr": template.get("heldout_psnr"),
        "template_heldout_ssim": template.get("heldout_ssim"),
        "features_heldout_cosine": features.get("heldout_cosine"),
        "painted_part": paint_part,
        "semantic_mask_heldout_iou_mean": float(np.mean(list(ious.values()))),
        "semantic_mask_heldout_iou": ious,
        "seconds": {k: round(v, 1) for k, v in seconds.items()},
        "config": to_dict(cfg),
    }
    write_json(cfg.out / "demo_summary.json", summary)
    return summary


DESCRIPTION = __doc__
NAME = "demo"
HELP = "run the whole pipeline on the built-in procedural object"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    add_options(parser, DemoConfig)


def run(args: argparse.Namespace) -> int:
    summary = run_demo(from_args(DemoConfig, args))
    out = Path(args.out)
    print("\n== sine demo: summary ==")
    for key in (
        "registered_views",
        "silhouette_iou_mean",
        "template_heldout_psnr",
        "template_heldout_ssim",
        "semantic_mask_heldout_iou_mean",
    ):
        print(f"  {key}: {summary[key]}")
    print(f"  seconds per stage: {summary['seconds']}")
    print(f"\nLook at: {out / 'run' / 'recon_contact_sheet.png'}")
    print(f"         {out / 'run' / 'template' / 'previews'}/ (held-out renders vs ground truth)")
    print(f"         {out / 'run' / 'features' / 'previews'}/ (feature-field PCA)")
    print(
        f"         {out / 'run' / 'edits' / 'demo' / 'semantic_masks' / 'overlay_contact_sheet.png'}"
    )
    print(f"Numbers: {out / 'demo_summary.json'}")
    return 0
