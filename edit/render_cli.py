"""`sine render RUN [--edit NAME] --out DIR`: frames, video and camera path of a run or an edit."""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

from render.configs import add_options, from_args, option, validate
from render.errors import SineError

NAME = "render"
HELP = "render an orbit, a camera path or the capture views (PNG frames, MP4)"
DESCRIPTION = """\
Renders the fitted template of RUN (or its edit --edit NAME at --strength) along a camera path:
an orbit around the up axis at the captures' mean elevation and distance (--orbit N, the default
with 60 frames), a nerfstudio camera_path.json (--camera-path), or the capture's own views
(--views train|test|all). Writes DIR/rgb/*.png, optional DIR/depth/ and DIR/opacity/ (colour
mapped), DIR/features/ (the DINO feature field of `sine features` as its first three PCA
components in RGB; the template's field, so not with --edit), DIR/compare/ (template | edit, with --compare), DIR/camera_path.json (the cameras used,
nerfstudio format) and an MP4 with --video.
"""


@dataclass
class RenderConfig:
    """Options of `sine render`."""

    orbit: int | None = option(None, "orbit with N frames (the default path: 60 frames)")
    camera_path: Path | None = option(None, "nerfstudio camera_path.json to render")
    views: str | None = option(
        None, "render the capture's views of a split", choices=["train", "test", "all"]
    )
    width: int | None = option(None, "image width, the height keeps the aspect (None: the path's)")
    video: Path | None = option(None, "also write the frames as this MP4")
    fps: float = option(24.0, "video frames per second")
    depth: bool = option(False, "also write colour-mapped depth images (DIR/depth/)")
    opacity: bool = option(False, "also write opacity images (DIR/opacity/)")
    features: bool = option(
        False, "also write feature-PCA images (DIR/features/; needs `sine features`, no --edit)"
    )
    compare: bool = option(False, "also write template | edit strips (DIR/compare/; needs --edit)")
    supersample: int | None = option(
        None,
        "rays per pixel side, box-filtered (antialiasing; s^2 times the time; None: the "
        "template's `sine fit --supersample`)",
        low=1,
    )
    chunk: int = option(16384, "rays rendered at once (lower it if memory is short)", low=1)
    device: str = option("auto", "torch device: auto, cpu or cuda", choices=["auto", "cpu", "cuda"])
    threads: int = option(0, "torch CPU threads (0: torch's default)")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="run directory with a fitted template")
    parser.add_argument("--out", type=Path, required=True, help="output folder")
    parser.add_argument("--edit", default=None, help="render the edit RUN/edits/NAME")
    parser.add_argument("--strength", type=float, default=1.0, help="edit strength (0..1)")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_options(parser, RenderConfig, shown=("orbit", "views", "video", "compare", "device"))


def path_cameras(run_dir, cfg: RenderConfig) -> list:
    """The cameras to render, from the chosen source (orbit by default)."""
    from recon.rundir import RunDir
    from render.camera_paths import orbit_cameras, read_camera_path

    sources = [cfg.orbit is not None, cfg.camera_path is not None, cfg.views is not None]
    if sum(sources) > 1:
        raise SineError("choose one of --orbit, --camera-path and --views")
    if cfg.camera_path is not None:
        return read_camera_path(cfg.camera_path, cfg.width)
    frames = RunDir(run_dir).load_cameras().frames
    if cfg.views is not None:
        cams = [c for c in frames if cfg.views == "all" or c.split == cfg.views]
        if not cams:
            raise SineError(f"{run_dir} has no {cfg.views} views")
        if cfg.width is not None:
            cams = [
                c.resized(cfg.width, max(1, round(c.height * cfg.width / c.width))) for c in cams
            ]
        return cams
    return orbit_cameras(frames, cfg.orbit if cfg.orbit is not None else 60, cfg.width)


def feature_images(run_dir, template, chunk: int):
    """camera -> (PCA coefficients [H, W, D], object mask [H, W]) of the run's feature field,
    rendered with the already loaded `template` scene's field and sampler."""
    from edit.feature_maps import FeatureMapRenderer

    renderer = FeatureMapRenderer(
        run_dir, str(template.device), render_scale=1.0, chunk=chunk, geometry=template
    )

    def feature_map(camera):
        feats, on_object = renderer(camera)
        return feats.permute(1, 2, 0).numpy(), on_object

    return feature_map


def run(args: argparse.Namespace) -> int:
    from edit.scene import load_scene
    from recon.rundir import RunDir
    from render.device import torch_threads
    from render.frames import render_frames
    from render.io import require_directory

    cfg = validate(from_args(RenderConfig, args))
    require_directory(args.out)
    RunDir(args.run).refuse_output_inside(args.out)
    if cfg.compare and args.edit is None:
        raise SineError("--compare shows template | edit: give --edit NAME")
    if cfg.features and args.edit is not None:
        raise SineError(
            "--features shows the template's DINO feature field (an edit does not change it): "
            "drop --edit, or render the features in a separate `sine render` call"
        )
    cameras = path_cameras(args.run, cfg)
    with torch_threads(cfg.threads):
        scene = load_scene(args.run, args.edit, args.strength, cfg.device, cfg.supersample)
        reference = None
        if cfg.compare:
            reference = load_scene(args.run, None, device=cfg.device, supersample=cfg.supersample)
        feature_map = feature_images(args.run, scene, cfg.chunk) if cfg.features else None
        summary = render_frames(
            scene,
            cameras,
            args.out,
            video=cfg.video,
            fps=cfg.fps,
            depth=cfg.depth,
            opacity=cfg.opacity,
            reference=reference,
            chunk=cfg.chunk,
            progress=not args.quiet,
            feature_map=feature_map,
        )
    video = f", video {summary['video']}" if summary["video"] else ""
    print(
        f"render: {summary['frames']} frames of {summary['width']}x{summary['height']} "
        f"({scene.name}) -> {args.out}{video}"
    )
    return 0
