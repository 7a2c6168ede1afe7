"""`sine synth`: render a synthetic turntable with ground truth (and optional GT edits)."""

from __future__ import annotations

import argparse

from render.configs import add_options, from_args

DESCRIPTION = """\
Renders a textured mesh (--mesh) or a built-in procedural object (--procedural
toycar|figurine|mug|chair) from a ring of cameras looking at the origin, by ray casting with
Lambertian + ambient shading under a fixed light. Writes images/, masks/, depth/ (camera-z .npy),
labels/ (uint16 part ids), parts.json, transforms.json (nerfstudio, OpenGL axes), cameras.json,
mesh.ply (the normalised ground-truth mesh with vertex colours) and synth.json. With --edit
geometric/texture, the edited object is rendered from the same cameras into edits/<kind>/ with
edit.json.
Every 8th view (7, 15, 23, ...) is a held-out "test" view.
"""


NAME = "synth"
HELP = "render a synthetic turntable with ground truth (images, masks, depth, parts, edits)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from recon.synth import SynthConfig

    add_options(
        parser,
        SynthConfig,
        shown=(
            "out",
            "mesh",
            "procedural",
            "views",
            "width",
            "height",
            "background",
            "edit",
            "format",
        ),
    )
    parser.add_argument(
        "--quiet", action="store_true", help="no progress bars, only the final summary line"
    )


def run(args: argparse.Namespace) -> int:
    from recon.rundir import RunDir
    from recon.synth import SynthConfig, synthesize
    from render.io import require_directory

    cfg = from_args(SynthConfig, args)
    require_directory(cfg.out, "--out")
    summary = synthesize(cfg, progress=not args.quiet)
    RunDir(cfg.out).append_config("synth", cfg)
    edits = ", ".join(summary["edits"]) or "none"
    print(
        f"synth: {summary['views']} views {cfg.width}x{cfg.height} of {summary['source']} -> "
        f"{summary['out']} (render {summary['seconds_render']:.2f} s, write "
        f"{summary['seconds_write']:.2f} s, total {summary['seconds_total']:.2f} s; "
        f"mask coverage {summary['mean_mask_coverage']:.1%}; edits: {edits})"
    )
    return 0
