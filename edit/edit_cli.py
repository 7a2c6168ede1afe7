"""`sine edit RUN --target IMG --view K`: learn an edit of the 3D object from one edited view."""

from __future__ import annotations

import argparse
from pathlib import Path

from render.configs import add_options, from_args

NAME = "edit"
HELP = "learn a 3D edit from one edited image of a view (RUN/edits/NAME/)"
DESCRIPTION = """\
Learns the editing field that turns the template of RUN into the object of the TARGET image, an
edited version of view K (make one with `sine snapshot` + any 2D editor, or `sine target`).

Geometry (--mode geometry): the target's silhouette comes from its alpha channel, --mask, or
background keying, in that order. The editable region is --region (a white-on-black PNG of the
part, at the working size), else where target and template differ. An ARAP shape prior is built
from dense correspondences between the template's view and the target (RUN/edits/NAME/
prior_mesh.ply and prior_preview.png: check it), then the editing field is trained with the
paper's losses. --method naive fine-tunes the template on the single view instead (a baseline).

Writes RUN/edits/NAME/ (target, region, prior mesh, edit_field.pt, metrics.json, previews/).
An interrupted edit resumes when re-run; changed options train it again; --force starts over.

examples:
  sine snapshot runs/car --view 9 --out view9.png      # edit view9.png in any 2D tool, then
  sine edit runs/car --target view9_edited.png --view 9 --name taller
  sine target runs/car --view 9 --warp "130,70>130,40" --out t.png && \\
      sine edit runs/car --target t.png --view 9 --name warp --symmetric
  sine render runs/car --edit taller --orbit 60 --video taller.mp4 --out renders/
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    from edit.geometry_edit import GeometryEditConfig

    parser.add_argument("run", type=Path, help="run directory with a fitted template")
    parser.add_argument("--target", type=Path, required=True, help="the edited image of view K")
    parser.add_argument(
        "--view", type=int, required=True, help="index K of the edited view (cameras.json order)"
    )
    parser.add_argument(
        "--mode", choices=["geometry"], default="geometry", help="what the edit changes"
    )
    parser.add_argument("--name", default="edit", help="the edit's name: RUN/edits/NAME")
    parser.add_argument(
        "--mask", type=Path, help="silhouette of the target (white = object) if it has no alpha"
    )
    parser.add_argument(
        "--region", type=Path, help="the editable part painted white on black in view K"
    )
    parser.add_argument("--force", action="store_true", help="start over, ignoring checkpoints")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_options(parser, GeometryEditConfig)


def run(args: argparse.Namespace) -> int:
    from edit.geometry_edit import GeometryEditConfig, run_geometry_edit

    cfg = from_args(GeometryEditConfig, args)
    metrics = run_geometry_edit(
        args.run,
        args.view,
        args.target,
        args.name,
        cfg,
        mask=args.mask,
        region=args.region,
        force=args.force,
        progress=not args.quiet,
    )
    where = args.run / "edits" / args.name
    if metrics.get("skipped"):
        print(f"edit {args.name}: already done with these options -> {where} (--force redoes it)")
        return 0
    print(
        f"edit {args.name} ({metrics['method']}): {metrics['iterations']} steps in "
        f"{metrics['train_seconds']:.0f} s; edited view: object PSNR "
        f"{metrics['edited_view_psnr_object']:.2f} dB, silhouette IoU "
        f"{metrics['edited_view_silhouette_iou']:.3f} -> {where} (look at edited_view.png, "
        f"prior_preview.png and previews/)"
    )
    return 0
