"""`sine eval RUN [--edit NAME] --gt DIR`: PSNR/SSIM of rendered views against ground truth."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "eval"
HELP = "PSNR/SSIM of the rendered template or edit against ground-truth images"
DESCRIPTION = """\
Renders RUN's template (or its edit --edit NAME) at the ground-truth views of --gt DIR (a folder
with cameras.json, images/ and optionally masks/: a run directory or a `sine synth` output such
as synth_out/edits/geometric; default: RUN itself, i.e. the template against its own captures)
and scores them with PSNR and SSIM (scikit-image): over the whole image, on the object's pixels
(ground-truth mask or rendered opacity > 0.5) and, with --region-masks DIR (DIR/<view>.png or
DIR/masks/<view>.png, e.g. the output of `sine masks`), inside the edit region and on the object
outside it. Views are matched to the run's cameras by file name. Writes the per-view and mean
metrics as JSON (RUN/edits/NAME/eval.json, RUN/template/eval.json without --edit, or --out) and
prints a table.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="run directory with a fitted template")
    parser.add_argument("--edit", default=None, help="evaluate the edit RUN/edits/NAME")
    parser.add_argument("--strength", type=float, default=1.0, help="edit strength (0..1)")
    parser.add_argument(
        "--gt", type=Path, default=None, help="ground-truth folder (default: RUN's captures)"
    )
    parser.add_argument(
        "--region-masks", type=Path, default=None, help="folder of edit-region masks per view"
    )
    parser.add_argument(
        "--split", default="all", choices=["all", "train", "test"], help="views to evaluate"
    )
    parser.add_argument("--out", type=Path, default=None, help="JSON file for the metrics")
    parser.add_argument("--chunk", type=int, default=16384, help="rays rendered at once")
    parser.add_argument(
        "--supersample",
        type=int,
        default=None,
        help="rays per pixel side, box-filtered (None: the template's `sine fit --supersample`)",
    )
    parser.add_argument(
        "--device", default="auto", choices=["auto", "cpu", "cuda"], help="torch device"
    )
    parser.add_argument("--quiet", action="store_true", help="no progress bar")


def evaluate(
    run_dir,
    edit=None,
    gt_dir=None,
    region_masks=None,
    split="all",
    strength=1.0,
    device="auto",
    chunk=16384,
    progress=True,
    supersample=None,
) -> dict:
    """Scores the template / edit of `run_dir` against `gt_dir` (see DESCRIPTION)."""
    from edit.scene import load_scene

    scene = load_scene(run_dir, edit, strength, device, supersample)
    return evaluate_scene(scene, gt_dir, region_masks, split, chunk, progress)


def evaluate_scene(
    scene, gt_dir=None, region_masks=None, split="all", chunk=16384, progress=True
) -> dict:
    """Scores a loaded scene (`edit.scene.load_scene`) against `gt_dir` (default: its run's
    captures) -> {"views": [per view], "mean": {...}, and what was scored}."""
    from render.evaluation import evaluate_views, load_gt_views

    gt_dir = Path(gt_dir) if gt_dir is not None else scene.run.root
    views = load_gt_views(gt_dir, scene.run.load_cameras(), split, region_masks)
    result = evaluate_views(scene, views, chunk, progress)
    result.update(
        scene=scene.name,
        strength=getattr(scene, "strength", None),  # edits only
        gt=str(gt_dir),
        region_masks=None if region_masks is None else str(region_masks),
        split=split,
        supersample=scene.supersample,
    )
    return result


def run(args: argparse.Namespace) -> int:
    from recon.rundir import RunDir
    from render.evaluation import format_table
    from render.io import write_json

    result = evaluate(
        args.run,
        args.edit,
        args.gt,
        args.region_masks,
        args.split,
        args.strength,
        args.device,
        args.chunk,
        not args.quiet,
        args.supersample,
    )
    run_dir = RunDir(args.run)
    out = args.out or (run_dir.edit(args.edit) if args.edit else run_dir.template) / "eval.json"
    write_json(out, result)
    print(format_table(result))
    print(f"eval: {result['mean']['n_views']} views ({result['scene']} vs {result['gt']}) -> {out}")
    return 0
