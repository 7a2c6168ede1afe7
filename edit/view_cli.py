"""`sine view RUN [--edit NAME] [--screenshot out.png]`: the Open3D viewer (or a PNG of it)."""

from __future__ import annotations

import argparse
import os
from pathlib import Path

import numpy as np

from render.errors import SineError

NAME = "view"
HELP = "look at the template and edited meshes with the cameras (Open3D), or save a screenshot"
DESCRIPTION = """\
Opens Open3D's viewer with RUN's template mesh (vertex colours from the fitted field) and, with
--edit NAME, the edited mesh beside it (key T shows/hides it), plus every capture camera as a
frustum (the edit's view, edit.json "view", highlighted in orange). --screenshot out.png renders
the same scene without a window or display (Mesa EGL offscreen) and exits. Without a display
and without --screenshot, run it under a virtual display: `xvfb-run -a sine view RUN`.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="run directory (with proxy_mesh.ply)")
    parser.add_argument("--edit", default=None, help="show the edit RUN/edits/NAME beside")
    parser.add_argument("--strength", type=float, default=1.0, help="edit strength (0..1)")
    parser.add_argument("--screenshot", type=Path, default=None, help="write this PNG and exit")
    parser.add_argument("--width", type=int, default=960, help="window / screenshot width")
    parser.add_argument("--height", type=int, default=540, help="window / screenshot height")
    parser.add_argument(
        "--no-colors",
        action="store_true",
        help="grey meshes (faster; without --edit no fitted field is needed: works after recon)",
    )
    parser.add_argument(
        "--device", default="auto", choices=["auto", "cpu", "cuda"], help="torch device"
    )


def edit_view_index(run, edit: str | None, frames) -> int | None:
    """Index of the edit's view (edit.json "view": an index or an image name), if any."""
    from render.io import read_json

    if edit is None or not (run.edit(edit) / "edit.json").is_file():
        return None
    view = read_json(run.edit(edit) / "edit.json").get("view")
    if isinstance(view, int) and 0 <= view < len(frames):
        return view
    if isinstance(view, str):
        for i, cam in enumerate(frames):
            if view in (cam.name, Path(cam.name).stem):
                return i
    return None


def viewer_scene(run_dir, edit=None, strength=1.0, colors=True, device="auto"):
    """The `ViewerScene` of a run (and edit): meshes, frustums, view direction."""
    from edit.scene import load_scene
    from recon.rundir import RunDir
    from render.viewer import build_scene

    run = RunDir(run_dir)
    frames = run.load_cameras().frames
    if colors or edit is not None:
        template = load_scene(run.root, None, device=device)
        template_mesh = template.colored_mesh() if colors else (*template.mesh(), None)
    else:
        from recon.fit_proxy import template_proxy

        run.require("proxy_mesh")
        m = run.read_proxy(template_proxy(run))
        template_mesh = (np.asarray(m.vertices), np.asarray(m.triangles), None)
    edited_mesh = None
    if edit is not None:
        scene = load_scene(run.root, edit, strength, device)
        edited_mesh = scene.colored_mesh() if colors else (*scene.mesh(), None)
    distance = float(np.mean([np.linalg.norm(c.center) for c in frames]))
    return build_scene(
        template_mesh,
        edited_mesh,
        frames,
        highlight=edit_view_index(run, edit, frames),
        frustum_size=0.06 * distance,
    )


def run(args: argparse.Namespace) -> int:
    from render.viewer import interactive, screenshot

    if args.screenshot is None and not (
        os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")
    ):
        raise SineError(
            "no display: pass --screenshot out.png to render the view to a PNG, "
            "or run under a virtual display (`xvfb-run -a sine view ...`)"
        )
    scene = viewer_scene(args.run, args.edit, args.strength, not args.no_colors, args.device)
    if args.screenshot is not None:
        screenshot(scene, args.screenshot, args.width, args.height)
        print(f"view: screenshot {args.width}x{args.height} -> {args.screenshot}")
        return 0
    interactive(scene, args.width, args.height)
    return 0
