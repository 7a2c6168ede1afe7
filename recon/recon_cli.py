"""`sine recon CAPTURE --out RUN`: the reconstruction pipeline from the command line."""

from __future__ import annotations

import argparse
from pathlib import Path

from recon.rundir import RunDir
from render.configs import add_options, from_args

DESCRIPTION = """\
Turntable-aware reconstruction as idempotent stages (ingest -> masks -> poses -> normalize ->
depth -> proxy_mesh -> report). Finished stages are skipped; --force redoes them. Writes
cameras.json, masks/, depth/, proxy_mesh.ply, recon_report.json and recon_contact_sheet.png into
the run directory. Self-checks after the poses and of the proxy mesh (do the cameras explain the
masks?) stop the run when they find it poor (--accept-poor-poses goes on); recon_report.json
gets a verdict.
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
    add_options(
        parser, IngestConfig, shown=("width", "frames", "format", "ignore_poses", "masks", "force")
    )
    add_options(parser, ReconConfig, shown=("mask_method", "depth_method", "accept_poor_poses"))


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
