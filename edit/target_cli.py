"""`sine target RUN --view K --out target.png OPERATION`: an editing target without a 2D editor.

Starts from the view's rendering or capture (edit/snapshot_cli.py), applies exactly one 2D
operation of edit/targets.py and writes the target as RGBA (alpha = the edited silhouette) plus a
before/after picture.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from render.configs import add_options, from_args
from render.errors import SineError

DESCRIPTION = """\
Makes an editing target from view --view of RUN with exactly one 2D operation (below).
Coordinates are pixels as an image editor shows them: x = column, y = row, from 0 at the top
left. Painted regions are PNGs of the run's working size, white = painted (paint over
`sine snapshot`'s picture). Writes OUT (RGBA: alpha is the edited silhouette) and
OUT_before_after.png. Modifiers: --warp with --anchor 'x,y;...' (points that stay put), --scale
with --center 'x,y' (its fixed point), --stretch-axis with --about C (the column or row that
stays put), --recolor with --saturation S (multiplies it), --paint with --flat (no shading).
"""

EXAMPLES = {
    "warp": '--warp "120,40>150,30;60,200>60,220"',
    "anchor": '--anchor "100,180;140,180"',
    "center": '--center "128,96"',
    "color": "--color 200,30,30",
}


# ---- parsing ------------------------------------------------------------------------------
def _number(text: str, what: str, example: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise SineError(
            f"cannot read {text.strip()!r} in {what} as a number; e.g. {example}"
        ) from None
    if not np.isfinite(value):
        raise SineError(f"{what} has a non-finite number {text!r}; e.g. {example}")
    return value


def parse_point(text: str, what: str, example: str) -> tuple[float, float]:
    """'x,y' -> (x, y)."""
    parts = text.split(",")
    if len(parts) != 2:
        raise SineError(f"{what}: {text.strip()!r} is not a point 'x,y'; e.g. {example}")
    return _number(parts[0], what, example), _number(parts[1], what, example)


def parse_points(text: str, what: str = "--anchor") -> list[tuple[float, float]]:
    """'x,y;x,y;...' -> [(x, y), ...]."""
    example = EXAMPLES["anchor"] if what == "--anchor" else EXAMPLES["center"]
    items = [t for t in text.split(";") if t.strip()]
    if not items:
        raise SineError(f"{what} is empty; e.g. {example}")
    return [parse_point(t, what, example) for t in items]


def parse_warp(text: str) -> list[tuple[tuple[float, float], tuple[float, float]]]:
    """'x0,y0>x1,y1;...' -> [((x0, y0), (x1, y1)), ...]."""
    example = EXAMPLES["warp"]
    items = [t for t in text.split(";") if t.strip()]
    if not items:
        raise SineError(f"--warp is empty; e.g. {example}")
    handles = []
    for item in items:
        ends = item.split(">")
        if len(ends) != 2:
            raise SineError(
                f"--warp: {item.strip()!r} is not a handle 'x0,y0>x1,y1' (from > to); "
                f"e.g. {example}"
            )
        handles.append(tuple(parse_point(e, "--warp", example) for e in ends))
    return handles


def parse_color(text: str) -> np.ndarray:
    """'R,G,B' with 0..255 values -> RGB [3] in [0, 1]."""
    parts = text.split(",")
    if len(parts) != 3:
        raise SineError(f"--color {text!r} is not 'R,G,B'; e.g. {EXAMPLES['color']}")
    rgb = np.array([_number(p, "--color", EXAMPLES["color"]) for p in parts], np.float32)
    if np.any(rgb < 0) or np.any(rgb > 255):
        raise SineError(f"--color values are 0..255, got {text!r}; e.g. {EXAMPLES['color']}")
    return rgb / 255.0


def load_region(path: Path, width: int, height: int, what: str = "--region") -> np.ndarray:
    """A painted-region PNG as bool [H, W], checked against the view's working size."""
    from render.io import read_mask

    path = Path(path)
    if not path.is_file():
        raise SineError(f"{what} image {path} does not exist")
    region = read_mask(path)
    if region.shape != (height, width):
        raise SineError(
            f"{what} {path} is {region.shape[1]}x{region.shape[0]} but the view is "
            f"{width}x{height}: paint over the view's snapshot (`sine snapshot`)"
        )
    if not region.any():
        raise SineError(f"{what} {path} is empty: paint the part in white")
    return region


# ---- the operation ------------------------------------------------------------------------
OPERATIONS = ("warp", "scale", "stretch_axis", "recolor", "paint")
# option -> the operation it belongs to (given with another operation, it is an error)
OWNED = {
    "anchor": "warp",
    "center": "scale",
    "factor": "stretch_axis",
    "about": "stretch_axis",
    "hue": "recolor",
    "saturation": "recolor",
    "color": "paint",
    "flat": "paint",
}
FLAGS = {"stretch_axis": "--stretch-axis", "scale": "--region ... --scale"}


def _given(value) -> bool:
    return value is not None and value is not False


def chosen_operation(args: argparse.Namespace) -> str:
    """The one operation named on the command line (SineError for none, several or stray options)."""
    given = [op for op in OPERATIONS if _given(getattr(args, op))]
    if len(given) != 1:
        names = ", ".join("--" + op.replace("_", "-") for op in given)
        raise SineError(
            ("several operations given (" + names + "); " if given else "no operation given; ")
            + f"choose exactly one: {EXAMPLES['warp']}, --region painted.png --scale 1.3, "
            "--stretch-axis x --factor 1.2, --recolor --region painted.png --hue 120, "
            f"--paint painted.png {EXAMPLES['color']}"
        )
    op = given[0]
    for name, owner in OWNED.items():
        if _given(getattr(args, name)) and owner != op:
            flag = FLAGS.get(owner, "--" + owner)
            raise SineError(f"--{name} belongs to {flag}, not to --{op.replace('_', '-')}")
    if args.region is not None and op in ("warp", "paint"):
        raise SineError(f"--region is not used by --{op} (paint: the region is --paint's PNG)")
    if op in ("scale", "recolor") and args.region is None:
        raise SineError(f"--{op} needs --region painted.png (the part to change)")
    if op == "stretch_axis" and args.factor is None:
        raise SineError(f"--stretch-axis {args.stretch_axis} needs --factor F (e.g. 1.2)")
    if op == "recolor" and args.hue is None and args.saturation is None:
        raise SineError("--recolor needs --hue DEG (e.g. --hue 120) and/or --saturation S")
    if op == "paint" and args.color is None:
        raise SineError(f"--paint needs --color R,G,B; e.g. {EXAMPLES['color']}")
    parsed(args)  # syntax errors now, before any rendering
    return op


def parsed(args: argparse.Namespace) -> dict:
    """The option strings of `args` parsed (handles, anchors, centre, colour)."""
    return {
        "handles": parse_warp(args.warp) if args.warp else [],
        "anchors": parse_points(args.anchor) if args.anchor else [],
        "center": parse_point(args.center, "--center", EXAMPLES["center"]) if args.center else None,
        "color": parse_color(args.color) if args.color else None,
    }


def load_regions(args: argparse.Namespace, width: int, height: int) -> dict:
    """The painted PNGs of `args` (--region, --paint) as bool [H, W], checked against the size."""
    return {
        "region": load_region(args.region, width, height) if args.region else None,
        "paint": load_region(args.paint, width, height, "--paint") if args.paint else None,
    }


def make_target(args: argparse.Namespace, view, regions: dict | None = None):
    """Applies the operation of `args` to the view -> (image, alpha, one-line summary)."""
    from edit import targets

    op = chosen_operation(args)
    p = parsed(args)
    h, w = view.alpha.shape
    regions = regions or load_regions(args, w, h)
    image, alpha, bg, region = view.image, view.alpha, view.background, regions["region"]
    if op == "warp":
        out, a = targets.warp_target(image, alpha, p["handles"], p["anchors"], background=bg)
        return out, a, f"warp ({len(p['handles'])} handles, {len(p['anchors'])} anchors)"
    if op == "scale":
        out, a = targets.scale_region(image, alpha, region, args.scale, p["center"], background=bg)
        return out, a, f"scale x{args.scale:g} of the painted part"
    if op == "stretch_axis":
        out, a = targets.stretch_axis(
            image, alpha, args.stretch_axis, args.factor, args.about, region, background=bg
        )
        where = "the painted part" if region is not None else "the object"
        return out, a, f"stretch {where} x{args.factor:g} along {args.stretch_axis}"
    part = (region if op == "recolor" else regions["paint"]) & (alpha >= 0.5)
    if not part.any():
        raise SineError(
            f"the painted region does not touch the object in view {view.index}: paint over "
            "the object's pixels (alpha >= 0.5 in `sine snapshot`)"
        )
    if op == "recolor":
        out = targets.recolor_region(image, part, args.hue or 0.0, args.saturation)
        return out, alpha, f"recolor hue {args.hue or 0:+g} deg of {int(part.sum())} pixels"
    out = targets.paint_region(image, part, p["color"], shading=not args.flat)
    return out, alpha, f"paint {int(part.sum())} pixels {args.color}"


def before_after_path(out: Path) -> Path:
    return Path(out).with_name(Path(out).stem + "_before_after.png")


NAME = "target"
HELP = "make an editing target from one view by a 2D operation (warp, scale, stretch, recolour)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from edit.snapshot_cli import ViewSourceConfig

    parser.add_argument("run", type=Path, help="run directory (with cameras.json)")
    parser.add_argument(
        "--view", required=True, help="view index 0..N-1 in cameras.json order, or an image name"
    )
    parser.add_argument("--out", type=Path, required=True, help="target PNG to write (RGBA)")
    ops = parser.add_argument_group("operation (exactly one)")
    ops.add_argument(
        "--warp", metavar="'x0,y0>x1,y1;...'", help="drag handle points from x0,y0 to x1,y1"
    )
    ops.add_argument("--anchor", metavar="'x,y;...'", help=argparse.SUPPRESS)
    ops.add_argument(
        "--region",
        type=Path,
        help="painted part (PNG of the working size, white = painted) for --scale and "
        "--recolor; with --stretch-axis, stretch only this part",
    )
    ops.add_argument("--scale", type=float, help="scale the --region part by this factor")
    ops.add_argument("--center", metavar="'x,y'", help=argparse.SUPPRESS)
    ops.add_argument("--stretch-axis", choices=["x", "y"], help="stretch along this image axis")
    ops.add_argument("--factor", type=float, help="--stretch-axis: stretch factor (e.g. 1.2)")
    ops.add_argument("--about", type=float, help=argparse.SUPPRESS)
    ops.add_argument("--recolor", action="store_true", help="rotate the hue of the --region part")
    ops.add_argument("--hue", type=float, help="--recolor: hue rotation in degrees (e.g. 120)")
    ops.add_argument("--saturation", type=float, help=argparse.SUPPRESS)
    ops.add_argument("--paint", type=Path, help="painted part (PNG) to fill with --color")
    ops.add_argument("--color", metavar="R,G,B", help="--paint: colour, 0..255 per channel")
    ops.add_argument("--flat", action="store_true", help=argparse.SUPPRESS)
    add_options(parser, ViewSourceConfig, shown=())


def run(args: argparse.Namespace) -> int:
    from edit.snapshot_cli import ViewSourceConfig, load_view, pick_view
    from edit.targets import before_after, write_rgba
    from recon.rundir import RunDir
    from render.io import write_image

    if args.out.suffix.lower() != ".png":
        raise SineError(f"--out {args.out} must be a .png (the target keeps its alpha)")
    RunDir(args.run).refuse_output_inside(args.out)
    chosen_operation(args)  # option errors before the (slow) rendering
    _, camera = pick_view(RunDir(args.run).load_cameras().frames, args.view)
    regions = load_regions(args, camera.width, camera.height)
    view = load_view(args.run, args.view, from_args(ViewSourceConfig, args))
    if view.note:
        print(f"target: {view.note}")
    image, alpha, summary = make_target(args, view, regions)
    write_rgba(args.out, image, alpha, view.background)
    side = before_after_path(args.out)
    write_image(side, before_after(view.image, image))
    changed = float(np.abs(image - view.image).max()) * 255 >= 0.5
    changed = changed or float(np.abs(alpha - view.alpha).max()) * 255 >= 0.5
    print(
        f"target: {summary} on view {view.index} ({view.camera.name}, {view.source}); object "
        f"{int((view.alpha >= 0.5).sum())} -> {int((alpha >= 0.5).sum())} pixels"
        + ("" if changed else " (warning: nothing changed)")
    )
    print(f"target: {args.out}")
    print(f"target: before/after {side}")
    return 0
