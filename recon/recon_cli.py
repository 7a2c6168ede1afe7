"""`sine recon CAPTURE --out RUN`: the reconstruction pipeline from the command line."""

from __future__ import annotations

import argparse
from pathlib import Path

from recon.rundir import RunDir
from render.configs import add_options, from_args

DESCRIPTION = """\
Reconstructs a capture into a run directory in stages (ingest, masks, poses, normalize, depth,
proxy_mesh, report); finished stages are skipped, --force redoes them. Look at
RUN/recon_contact_sheet.png: a self-check that finds the poses poor stops the run
(--accept-poor-poses goes on). An object in a room: --object-box around it in one view.
"""

NAME = "recon"
HELP = "reconstruct a capture: masks, poses, normalisation, depth, proxy mesh, report"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from recon.ingest import IngestConfig
    from recon.recon_config import ReconConfig

    parser.add_argument(
        "capture",
        type=Path,
        nargs="?",
        help="capture to reconstruct (omit to continue an ingested run)",
    )
    parser.add_argument("--out", type=Path, required=True, help="run directory to write")
    add_options(parser, IngestConfig, shown=("width", "frames", "ignore_poses", "masks", "force"))
    add_options(
        parser,
        ReconConfig,
        shown=("mask_method", "depth_method", "accept_poor_poses", "object_box", "object_view"),
    )


def run(args) -> int:
    from recon.ingest import IngestConfig
    from recon.pipeline import run_recon
    from recon.recon_config import ReconConfig

    report = run_recon(
        args.capture, RunDir(args.out), from_args(ReconConfig, args), from_args(IngestConfig, args)
    )
    keys = (
        "registered_views",
        "total_views",
        "mean_reprojection_error_px",
        "mask_coverage_mean",
        "depth_source",
        "proxy_triangles",
        "proxy_closed",
        "silhouette_iou_mean",
        "verdict",
    )
    for key in keys:
        print(f"{key}: {report.get(key)}")
    for reason in report.get("verdict_reasons", []):
        print(f"  poor: {reason}")
    if report.get("unregistered"):
        print(f"unregistered views (dropped): {', '.join(report['unregistered'])}")
    print(f"report: {RunDir(args.out).recon_report}")
    return 0
