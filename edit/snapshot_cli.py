"""`sine snapshot RUN --view K --out view.png`: one view of a run as an RGBA PNG to edit.

The template's rendering of the view (alpha = rendered opacity) or the capture (the run's working
image, alpha = its mask), at the run's working size (the camera's width x height in
cameras.json). The PNG's RGB is straight colour: composited over the run's background colour it
is the rendering.
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from render.configs import add_options, from_args, option
from render.errors import SineError

DESCRIPTION = """\
Writes view --view of RUN as an RGBA PNG for editing in any 2D tool (or with `sine target`):
the template's rendering (alpha = opacity; composited over the run's background colour the PNG
is the rendering) or the capture (the run's working image, alpha = its mask), at the run's
working size. Views are
numbered 0..N-1 in cameras.json order (an image name works too). --source auto renders when
RUN/template/field.pt exists (after `sine fit`) and uses the capture otherwise.
"""


@dataclass
class ViewSourceConfig:
    """Where a view's starting image comes from (shared by `sine snapshot` and `sine target`)."""

    source: str = option(
        "auto",
        "starting image: the template's rendering, the capture (image + mask), or auto "
        "(render when RUN/template/field.pt exists, else the capture)",
        choices=["auto", "render", "capture"],
    )
    device: str = option("auto", "torch device: auto, cpu or cuda", choices=["auto", "cpu", "cuda"])
    threads: int = option(0, "torch CPU threads (0: torch's default)")
    chunk: int = option(16384, "rays per chunk when rendering")


@dataclass
class View:
    """One view's starting image: image [H, W, 3] in [0, 1], alpha [H, W] in [0, 1]."""

    index: int
    camera: object
    image: np.ndarray
    alpha: np.ndarray
    source: str  # "render" or "capture"
    background: np.ndarray  # [3] render background, or [H, W, 3] capture backdrop
    note: str = ""


def pick_view(cameras, view: str | int):
    """`--view`: 0-based index into cameras.json (or an image name / stem) -> (index, camera)."""
    text = str(view).strip()
    n = len(cameras)
    if text.lstrip("-").isdigit():
        i = int(text)
        if not 0 <= i < n:
            raise SineError(f"--view {i} is out of range: valid views are 0..{n - 1}")
        return i, cameras[i]
    for i, cam in enumerate(cameras):
        if text in (cam.name, Path(cam.name).stem):
            return i, cam
    raise SineError(
        f"--view {text!r} is neither a view index (0..{n - 1}) nor an image of the run "
        f"(e.g. {cameras[0].name})"
    )


def resolve_source(run, source: str) -> str:
    if source == "auto":
        return "render" if (run.template / "field.pt").is_file() else "capture"
    if source == "render" and not (run.template / "field.pt").is_file():
        raise SineError(
            f"{run.template / 'field.pt'} not found: run `sine fit {run.root}` first, "
            "or use --source capture"
        )
    return source


def render_view(run, camera, cfg: ViewSourceConfig) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The template's rendering of `camera` -> (rgb [H, W, 3], opacity [H, W], background [3])."""
    import torch

    from edit.template_scene import load_template_scene
    from render.device import pick_device, torch_threads

    with torch_threads(cfg.threads), torch.no_grad():
        template = load_template_scene(run, pick_device(cfg.device))
        out = template.render_view(camera, cfg.chunk)
        bg = template.background().detach().float().cpu().numpy().reshape(3)
    rgb = np.clip(out["rgb"], 0.0, 1.0).astype(np.float32)
    return rgb, np.clip(out["opacity"], 0.0, 1.0).astype(np.float32), bg


def capture_view(run, camera) -> tuple[np.ndarray, np.ndarray, str]:
    """The run's working image and mask of `camera` -> (image, alpha, note), at the camera's size."""
    import cv2

    from render.io import read_image, read_mask

    path = run.image_path(camera.name)
    if not path.is_file():
        raise SineError(f"{path} is missing (cameras.json names it); re-run `sine ingest`")
    image = read_image(path)
    size = (camera.width, camera.height)
    if image.shape[:2] != (camera.height, camera.width):
        image = cv2.resize(image, size, interpolation=cv2.INTER_AREA)
    mask_path = run.mask_path(camera.name)
    if not mask_path.is_file():
        note = f"no mask {mask_path}: alpha is opaque everywhere"
        return image, np.ones(image.shape[:2], np.float32), note
    mask = read_mask(mask_path).astype(np.uint8)
    if mask.shape != (camera.height, camera.width):
        mask = cv2.resize(mask, size, interpolation=cv2.INTER_NEAREST)
    return image, mask.astype(np.float32), ""


def load_view(run_dir, view: str | int, cfg: ViewSourceConfig | None = None) -> View:
    """View `view` of the run at `run_dir`, rendered or captured (cfg.source)."""
    from edit.targets import inpaint_backdrop
    from recon.rundir import RunDir

    cfg = cfg or ViewSourceConfig()
    run = RunDir(run_dir)
    index, camera = pick_view(run.load_cameras().frames, view)
    source = resolve_source(run, cfg.source)
    if source == "render":
        image, alpha, bg = render_view(run, camera, cfg)
        return View(index, camera, image, alpha, source, bg)
    image, alpha, note = capture_view(run, camera)
    return View(index, camera, image, alpha, source, inpaint_backdrop(image, alpha), note)


def snapshot(run_dir, view: str | int, out, cfg: ViewSourceConfig | None = None) -> View:
    """Writes the view as an RGBA PNG at `out`; returns it."""
    from edit.targets import write_rgba

    v = load_view(run_dir, view, cfg)
    write_rgba(out, v.image, v.alpha, v.background)
    return v


NAME = "snapshot"
HELP = "one view of a run (rendered or captured) as an RGBA PNG to edit"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="run directory (with cameras.json)")
    parser.add_argument(
        "--view",
        required=True,
        help="view index 0..N-1 in cameras.json order, or an image name",
    )
    parser.add_argument("--out", type=Path, required=True, help="output PNG (RGBA)")
    add_options(parser, ViewSourceConfig, shown=("source", "device"))


def run(args: argparse.Namespace) -> int:
    from recon.rundir import RunDir

    RunDir(args.run).refuse_output_inside(args.out)
    v = snapshot(args.run, args.view, args.out, from_args(ViewSourceConfig, args))
    if v.note:
        print(f"snapshot: {v.note}")
    h, w = v.alpha.shape
    print(
        f"snapshot: view {v.index} ({v.camera.name}, {v.source}, {w}x{h}, "
        f"{(v.alpha >= 0.5).mean():.1%} object) -> {args.out}"
    )
    return 0
