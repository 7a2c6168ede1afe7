"""`sine ingest CAPTURE --out RUN`: a capture in any supported format -> a run directory."""

from __future__ import annotations

import argparse
from pathlib import Path

from recon.ingest import IngestConfig, ingest_capture
from recon.rundir import RunDir
from render.configs import add_options, from_args
from render.io import require_directory

DESCRIPTION = """\
Reads a capture into a run directory: working images (undistorted, resized to --width),
captures.json, and cameras.json / masks / depth when the capture carries them. Formats: a folder
of images (or its images/ subfolder), a video file, a NeRF/nerfstudio transforms.json, a COLMAP
model (sparse/0 + images/), a Middlebury ring (*_par.txt), a NeuS/IDR folder
(cameras_sphere.npz), or images with per-image 3x4 projection matrices (<stem>_P.txt or
<stem>.P). Running it again with the same capture and options does nothing (use --force).
"""

NAME = "ingest"
HELP = "read a capture (images, video, transforms.json, COLMAP, ...) into a run directory"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("capture", type=Path, metavar="CAPTURE", help="the capture to read")
    parser.add_argument(
        "--out", type=Path, required=True, metavar="RUN", help="run directory to write"
    )
    add_options(parser, IngestConfig)


def run(args: argparse.Namespace) -> int:
    cfg = from_args(IngestConfig, args)
    rundir = RunDir(require_directory(args.out, "--out"))
    summary = ingest_capture(args.capture, rundir, cfg)
    if summary["skipped"]:
        print(
            f"{rundir.root}: already holds this capture with the same options "
            f"({summary['views']} views); nothing to do (use --force to redo)"
        )
        return 0
    rundir.append_config("ingest", cfg)
    size = summary["working_size"]
    if summary["source_size"] != size:
        size += f" (from {summary['source_size']})"
    print(f"ingested {summary['views']} views from {args.capture} (format: {summary['format']})")
    print(f"  splits: {summary['train']} train / {summary['test']} test")
    print(f"  poses: {'yes (cameras.json)' if summary['poses'] else 'no'}")
    print(f"  working size: {size}")
    if summary["masks"] or summary["depth"] or summary["undistorted"]:
        print(
            f"  masks: {summary['masks']}, depth maps: {summary['depth']}, "
            f"undistorted: {summary['undistorted']}"
        )
    for note in summary["notes"]:
        print(f"  note: {note}")
    print(f"  run directory: {rundir.root} ({summary['seconds']:.1f} s)")
    return 0
