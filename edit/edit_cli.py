"""`sine edit RUN --target IMG --view K`: learn an edit of the 3D object from one edited view."""

from __future__ import annotations

import argparse
from pathlib import Path

from render.configs import add_options, from_args
from render.errors import SineError

NAME = "edit"
HELP = "learn a 3D edit from one edited image of a view (RUN/edits/NAME/)"
DESCRIPTION = """\
Learns the editing field that turns the template of RUN into the object of TARGET, an edited
image of view K (`sine snapshot` + any 2D editor, or `sine target`), and writes RUN/edits/NAME/.

  geometry  the target's silhouette (alpha, --mask, or keying) drives an ARAP shape prior
            (prior_preview.png: check it) and the paper's losses; --region limits the edit
  texture   the target is view K repainted (--region: the repainted part), or --reference
            PHOTO gives a look to take; semantic masks from `sine features` keep the rest
  hybrid    the shape, then the colours: one --target that changes both, or
            --target-geometry IMG with --target-texture IMG (view K of the new shape
            repainted) and --region-texture PNG when the repainted part differs from --region

An interrupted edit resumes when re-run; changed settings train it again; --force starts over.

examples:
  sine edit runs/car --target view9_edited.png --view 9 --name taller
  sine edit runs/car --target red.png --view 9 --region part.png --mode texture --name red
  sine edit runs/car --reference photo.png --view 9 --mode texture --name look
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    import dataclasses

    from edit.geometry_config import GeometryEditConfig
    from edit.texture_config import TextureEditConfig

    parser.add_argument("run", type=Path, help="run directory with a fitted template")
    parser.add_argument(
        "--target", type=Path, help="the edited image of view K (texture: or --reference)"
    )
    parser.add_argument(
        "--view", type=int, required=True, help="index K of the edited view (cameras.json order)"
    )
    parser.add_argument(
        "--mode",
        choices=["geometry", "texture", "hybrid"],
        default="geometry",
        help="what the edit changes (hybrid: shape, then colours)",
    )
    parser.add_argument("--target-geometry", type=Path, help=argparse.SUPPRESS)
    parser.add_argument("--target-texture", type=Path, help=argparse.SUPPRESS)
    parser.add_argument(
        "--region-texture",
        type=Path,
        help=argparse.SUPPRESS,  # described above
    )
    parser.add_argument(
        "--reference", type=Path, help="texture: a photo of another object whose look to take"
    )
    parser.add_argument("--name", default="edit", help="the edit's name: RUN/edits/NAME")
    parser.add_argument(
        "--mask", type=Path, help="the target's silhouette (white = object) without alpha"
    )
    parser.add_argument(
        "--region", type=Path, help="the editable part painted white on black in view K"
    )
    parser.add_argument("--force", action="store_true", help="start over, ignoring checkpoints")
    parser.add_argument("--quiet", action="store_true", help="no progress bar")
    add_options(parser, GeometryEditConfig, shown=("preset", "device"))
    # options of both modes have one default (tests/test_edit_texture.py checks): added once
    shared = tuple(f.name for f in dataclasses.fields(GeometryEditConfig))
    add_options(parser, TextureEditConfig, skip=shared, shown=())


def run(args: argparse.Namespace) -> int:
    hybrid_only = ("target_geometry", "target_texture", "region_texture")
    given = [f"--{k.replace('_', '-')}" for k in hybrid_only if getattr(args, k) is not None]
    if args.mode != "hybrid" and given:
        raise SineError(f"{' and '.join(given)}: for --mode hybrid only (other modes: --target)")
    learn, summary = {
        "geometry": (_learn_geometry, _geometry_summary),
        "texture": (_learn_texture, _texture_summary),
        "hybrid": (_learn_hybrid, _hybrid_summary),
    }[args.mode]
    metrics = learn(args, force=args.force, progress=not args.quiet)
    where = args.run / "edits" / args.name
    if metrics.get("skipped"):
        print(f"edit {args.name}: already done with these options -> {where} (--force redoes it)")
    else:
        print(summary(args, metrics, where))
    return 0


def _learn_geometry(args: argparse.Namespace, **common) -> dict:
    from edit.geometry_config import GeometryEditConfig
    from edit.geometry_edit import run_geometry_edit

    if args.reference is not None:
        raise SineError("--reference is for --mode texture or hybrid")
    if args.target is None:
        raise SineError("--target is required (the edited image of view K)")
    cfg = from_args(GeometryEditConfig, args)
    return run_geometry_edit(
        args.run, args.view, args.target, args.name, cfg, args.mask, args.region, **common
    )


def _geometry_summary(args: argparse.Namespace, metrics: dict, where: Path) -> str:
    return (
        f"edit {args.name} ({metrics['method']}): {metrics['iterations']} steps in "
        f"{metrics['train_seconds']:.0f} s; edited view: object PSNR "
        f"{metrics['edited_view_psnr_object']:.2f} dB, silhouette IoU "
        f"{metrics['edited_view_silhouette_iou']:.3f} -> {where} (look at edited_view.png, "
        f"prior_preview.png and previews/)"
    )


def _learn_texture(args: argparse.Namespace, **common) -> dict:
    from edit.texture_config import TextureEditConfig
    from edit.texture_edit import run_texture_edit

    if args.mask is not None:
        raise SineError("--mask is for --mode geometry (a texture edit keeps the silhouette)")
    cfg = from_args(TextureEditConfig, args)
    return run_texture_edit(
        args.run, args.view, args.target, args.name, cfg, args.region, args.reference, **common
    )


def _texture_summary(args: argparse.Namespace, metrics: dict, where: Path) -> str:
    fit = ""
    if "edited_view_psnr_region" in metrics:
        fit = f"edited part of view {args.view}: PSNR {metrics['edited_view_psnr_region']:.2f} dB, "
    kept = metrics.get("unedited_view_psnr")
    kept = f"unedited pixels {kept:.2f} dB" if kept is not None else "no unedited pixels"
    lines = [
        f"edit {args.name} (texture, {metrics['method']}): {metrics['iterations']} steps in "
        f"{metrics['train_seconds']:.0f} s; {fit}{kept} -> {where} (look at edited_view.png "
        f"and previews/)"
    ]
    mirror = metrics.get("mirror") or {}
    if mirror.get("pixels"):  # the automatic mirroring's verdict
        done = "mirrored" if mirror["mirrored"] else "not mirrored"
        lines.append(
            f"the painting {done} across the proxy's mirror plane: the far side's masks agree "
            f"with its mirror image at IoU {mirror['agreement']:.2f} "
            f"(symmetric_agreement {args.symmetric_agreement})"
        )
    return "\n".join(lines)


def _learn_hybrid(args: argparse.Namespace, **common) -> dict:
    from edit.geometry_config import GeometryEditConfig
    from edit.hybrid_edit import run_hybrid_edit
    from edit.texture_config import TextureEditConfig

    return run_hybrid_edit(
        args.run,
        args.view,
        args.name,
        from_args(GeometryEditConfig, args),
        from_args(TextureEditConfig, args),
        target=args.target,
        target_geometry=args.target_geometry,
        target_texture=args.target_texture,
        reference=args.reference,
        mask=args.mask,
        region=args.region,
        region_texture=args.region_texture,
        **common,
    )


def _hybrid_summary(args: argparse.Namespace, metrics: dict, where: Path) -> str:
    fit = ""
    if "edited_view_psnr_region" in metrics:
        fit = f", recoloured part PSNR {metrics['edited_view_psnr_region']:.2f} dB"
    return (
        f"edit {args.name} (hybrid): {metrics['geometry_iterations']} geometric + "
        f"{metrics['texture_iterations']} texture steps in {metrics['train_seconds']:.0f} s; "
        f"view {args.view}: silhouette IoU {metrics['edited_view_silhouette_iou']:.3f}{fit} -> "
        f"{where} (look at edited_view.png, geometry/prior_preview.png and previews/)"
    )
