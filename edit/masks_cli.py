"""`sine masks RUN --view K --region painted.png --out DIR`: semantic masks in every view
(the stage is edit/part_masks.py)."""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from render.configs import add_options, from_args

DESCRIPTION = """\
Semantic masks (SINE Sec. 3): renders the distilled DINO feature field of RUN at the editing view
--view (index into cameras.json or image name), samples features inside the painted region
(--region: a PNG of the run's working-image size, white = painted), fits K-means centres to them
and to the rest of the object, and marks a pixel of any view editable when its normalised feature
is nearer to the painted part's centres than to the rest's (--rule contrast, default) or within
--threshold of them (--rule threshold, the paper's rule). With the contrast rule each pixel's 3D
surface point counts beside its feature (--spatial; 0 for features only): surface that looks like
the painted part but lies among the rest of the object goes with the rest. Paint the whole part
as the editing view shows it: with the contrast rule, what is left unpainted counts as the rest
of the object. Mask
edges are snapped to the view's colour edges (guided filter; --no-refine to skip). Writes
DIR/masks/<view>.png, DIR/overlay_contact_sheet.png, DIR/semantic_centres.npy (and
semantic_rest_centres.npy; with --spatial, the centres' surface points *_centre_points.npy) and
DIR/metrics.json.
"""


NAME = "masks"
HELP = "semantic masks of a painted part in every view (DINO feature field + K-means)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from edit.part_masks import MasksConfig
    from edit.semantic_masks import SemanticMaskConfig

    parser.add_argument("run", type=Path, help="run directory with a feature field (sine features)")
    parser.add_argument(
        "--view", required=True, help="editing view: index into cameras.json or image name"
    )
    parser.add_argument(
        "--region",
        type=Path,
        required=True,
        help="PNG of the working-image size, white where the part to edit is painted",
    )
    parser.add_argument("--out", type=Path, required=True, help="output directory")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_options(parser, SemanticMaskConfig, shown=("num_clusters",))
    add_options(parser, MasksConfig, shown=("device",))


def run(args: argparse.Namespace) -> int:
    from edit.part_masks import MasksConfig, semantic_masks
    from edit.semantic_masks import SemanticMaskConfig

    m = semantic_masks(
        args.run,
        args.view,
        args.region,
        args.out,
        from_args(MasksConfig, args),
        from_args(SemanticMaskConfig, args),
        progress=not args.quiet,
    )
    fractions = [v["editable_fraction_of_object"] for v in m["per_view"].values()]
    print(
        f"masks: {m['views']} views from {m['region_pixels_on_object']} painted pixels in "
        f"{m['edit_view']} ({m['seconds_per_view']:.2f} s/view, total {m['seconds_total']:.1f} s); "
        f"editable {np.mean(fractions):.1%} of the object on average -> {args.out}"
    )
    return 0
