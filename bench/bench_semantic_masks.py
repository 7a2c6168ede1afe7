"""Semantic masks end to end: synth -> recon (known poses) -> fit -> features -> masks, per part.

A procedural object (toycar: body, cabin, wheels; figurine: base, body, head, hat) is rendered as
a turntable with ground-truth part labels; one part is painted in the editing view (its GT label,
eroded by a few pixels, as a user's stroke would stay inside the part); the masks of every view
(the feature maps `sine masks` renders, each mask rule in turn) are compared with that part's GT
pixels. Prints per-part IoU / precision / recall (mean over the held-out test views, which the
feature field never saw, and over every other view) and the stage timings.

    .venv/bin/python bench/bench_semantic_masks.py [--work /tmp/sine_bench_masks] [--views 36]
        [--object toycar] [--size 256] [--fit-iterations 300] [--feature-iterations 600]
        [--edit-views 2 11 | all] [--rules contrast+refine threshold] [--crop object]

Finished stages are reused when re-run with the same --work folder (delete it to start over).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see sine_cli.py

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))


def stage(name: str, timings: dict, fn, *args, **kwargs):
    t0 = time.perf_counter()
    out = fn(*args, **kwargs)
    timings[name] = time.perf_counter() - t0
    print(f"[bench] {name}: {timings[name]:.1f} s", flush=True)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--work", type=Path, default=Path("/tmp/sine_bench_masks"), help="work folder")
    ap.add_argument("--views", type=int, default=36, help="turntable views")
    ap.add_argument("--object", default="toycar", choices=["toycar", "figurine"], help="object")
    ap.add_argument("--size", type=int, default=256, help="image width = height")
    ap.add_argument("--fit-iterations", type=int, default=300, help="template fit steps")
    ap.add_argument("--fit-table", type=int, default=15, help="template log2 hash-table size")
    ap.add_argument("--feature-iterations", type=int, default=600, help="feature field steps")
    ap.add_argument("--short-side", type=int, default=224, help="DINO input short side")
    ap.add_argument("--crop", default="object", choices=["object", "image"], help="DINO input")
    ap.add_argument("--space", default="centred", choices=["centred", "dino"], help="mask space")
    ap.add_argument(
        "--rules",
        nargs="+",
        default=["contrast+refine", "contrast", "threshold"],
        choices=["contrast+refine", "contrast", "threshold+refine", "threshold"],
        help="mask rules compared (+refine: edges guided by the view's image)",
    )
    ap.add_argument(
        "--edit-views",
        nargs="+",
        default=["2", "11"],
        help="indices of editing views, or 'all' (every training view: per-part summary only)",
    )
    ap.add_argument(
        "--render-scale", type=float, default=0.5, help="feature maps rendered at this scale"
    )
    ap.add_argument("--erode", type=int, default=2, help="erode the painted GT part by N pixels")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    args = ap.parse_args()

    import cv2
    import torch

    from edit.feature_field_fit import FeaturesConfig, distill_features
    from edit.feature_maps import FeatureMapRenderer
    from edit.part_masks import view_image
    from edit.semantic_masks import SemanticMaskConfig, SemanticMasks
    from recon.fit import fit_template
    from recon.fit_config import FitConfig
    from recon.ingest import IngestConfig
    from recon.pipeline import run_recon
    from recon.recon_config import ReconConfig
    from recon.rundir import RunDir
    from recon.synth import SynthConfig, synthesize
    from render.io import read_json, read_label_map

    if args.threads:
        torch.set_num_threads(args.threads)
    work = args.work
    synth_dir, run = work / "synth", RunDir(work / "run")
    timings: dict[str, float] = {}
    if not (synth_dir / "parts.json").is_file():
        cfg = SynthConfig(
            out=synth_dir,
            procedural=args.object,
            views=args.views,
            width=args.size,
            height=args.size,
        )
        stage("synth", timings, synthesize, cfg, progress=False)
    if not run.proxy_mesh.is_file():
        stage(
            "recon",
            timings,
            run_recon,
            synth_dir,
            run,
            ReconConfig(),
            IngestConfig(width=args.size),
        )
    fit_cfg = FitConfig(iterations=args.fit_iterations, log2_table=args.fit_table, previews=0)
    fit = stage("fit", timings, fit_template, run.root, fit_cfg, progress=False)
    feat_cfg = FeaturesConfig(
        iterations=args.feature_iterations,
        short_side=args.short_side,
        crop=args.crop,
    )
    feat_metrics = stage("features", timings, distill_features, run.root, feat_cfg, progress=False)

    parts = {int(k): v for k, v in read_json(synth_dir / "parts.json").items()}
    cams = run.load_cameras().frames
    labels = {
        c.name: read_label_map(synth_dir / "labels" / (Path(c.name).stem + ".png")) for c in cams
    }
    t0 = time.perf_counter()
    render = FeatureMapRenderer(run.root, space=args.space, render_scale=args.render_scale)
    maps = {c.name: render(c) for c in cams}  # name -> (features [C, H, W], object [H, W])
    images = {c.name: view_image(run, c) for c in cams}
    seconds_render = (time.perf_counter() - t0) / len(cams)
    kernel = np.ones((2 * args.erode + 1, 2 * args.erode + 1), np.uint8)
    rows, seconds_masks = [], []
    if args.edit_views == ["all"]:
        edit_views = [i for i, c in enumerate(cams) if c.split == "train"]
    else:
        edit_views = [int(v) for v in args.edit_views]
    for ev in edit_views:
        edit = cams[ev]
        feats, on_object = maps[edit.name]
        for part, name in parts.items():
            region = labels[edit.name] == part
            if args.erode:
                region = cv2.erode(region.astype(np.uint8), kernel) > 0
            region &= on_object
            for rule in args.rules:
                t0 = time.perf_counter()
                cfg = SemanticMaskConfig(rule=rule.split("+")[0], refine=rule.endswith("+refine"))
                masks = SemanticMasks(feats, region, cfg, object_mask=on_object)
                stats: dict[str, list] = {"test": [], "all": []}
                for c in cams:
                    if c.name == edit.name:
                        continue
                    feats_c, object_c = maps[c.name]
                    mask = masks.mask(feats_c, images[c.name], object_c).numpy() & object_c
                    gt = labels[c.name] == part
                    inter, union = (mask & gt).sum(), (mask | gt).sum()
                    s = (inter / max(union, 1), inter / max(mask.sum(), 1), inter / gt.sum())
                    stats["all"].append(s)
                    if c.split != "train":
                        stats["test"].append(s)
                seconds_masks.append((time.perf_counter() - t0) / (len(cams) - 1))
                test, every = np.mean(stats["test"], axis=0), np.array(stats["all"])
                iou_all, iou_min = every[:, 0].mean(), every[:, 0].min()
                rows.append((edit.name, name, rule, int(region.sum()), *test, iou_all, iou_min))

    print(
        f"\nsemantic masks: {args.object} {args.views} views {args.size}x{args.size}, painted = GT "
        f"part eroded {args.erode} px, space {args.space}, render scale {args.render_scale}, DINO "
        f"{args.crop} crop short side {args.short_side}, K=15, 1000 samples (threshold rule: 0.5)"
    )
    print(
        f"{'edit view':<10} {'part':<8} {'rule':<16} {'painted':>8} {'IoU test':>9} "
        f"{'prec test':>9} {'rec test':>9} {'IoU all':>8} {'IoU min':>8}"
    )
    for view, name, rule, px, iou, prec, rec, iou_all, iou_min in rows:
        if len(edit_views) <= 8:
            print(
                f"{view:<10} {name:<8} {rule:<16} {px:>8} {iou:>9.3f} {prec:>9.3f} {rec:>9.3f} "
                f"{iou_all:>8.3f} {iou_min:>8.3f}"
            )
    print(f"\nper part over the {len(edit_views)} editing views (mean test IoU of each)")
    print(f"{'part':<8} {'rule':<16} {'mean':>6} {'median':>7} {'min':>6} {'>= 0.8':>7}")
    for name in parts.values():
        for rule in args.rules:
            ious = np.array([r[4] for r in rows if r[1] == name and r[2] == rule])
            print(
                f"{name:<8} {rule:<16} {ious.mean():>6.3f} {np.median(ious):>7.3f} "
                f"{ious.min():>6.3f} {np.mean(ious >= 0.8):>7.0%}"
            )
    n_test = sum(1 for c in cams if c.split != "train")
    print(f"(test: the {n_test} held-out views, never seen by the fit or the feature field;")
    print(" all: every view but the editing view; painted: pixels of the painted region)")
    print("\ntimings (s; this run, finished stages reused show as absent)")
    for key, value in timings.items():
        print(f"  {key:<10} {value:8.1f}")
    print(
        f"  fit: held-out PSNR {fit.get('heldout_psnr', float('nan')):.2f} dB; features: DINO "
        f"{feat_metrics['dino_seconds']:.1f} s, ray pool {feat_metrics['pool_seconds']:.1f} s, "
        f"training {feat_metrics['train_seconds']:.1f} s ({feat_metrics['iterations']} steps), "
        f"held-out rel. error {feat_metrics['heldout_rel_error']:.3f}, centred cosine "
        f"{feat_metrics['heldout_centred_cosine']:.3f}"
    )
    print(
        f"  masks: feature render {seconds_render:.2f} s per view, K-means + distances "
        f"{np.mean(seconds_masks):.3f} s per view"
    )


if __name__ == "__main__":
    main()
