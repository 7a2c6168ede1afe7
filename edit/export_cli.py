"""`sine export RUN [--edit NAME] --out mesh.ply|.glb|.obj`: the scene's coloured mesh."""

from __future__ import annotations

import argparse
from pathlib import Path

NAME = "export"
HELP = "export the (edited) mesh with vertex colours (PLY, GLB, OBJ)"
DESCRIPTION = """\
Writes the proxy mesh of RUN (for --edit NAME: the proxy warped by the edit) with vertex colours
from the (edited) radiance field: each vertex gets the colour a camera looking straight at the
surface there sees (a short ray along the inward normal through the vertex, volume rendered).
Coordinates are in the capture's original units and frame (cameras.json "normalization" undone:
x = rotation^T x_run / scale + center) unless --normalized keeps the run's units (object in the
unit sphere, up = +z). The format follows the file name: .ply, .glb or .obj (vertex colours in
each; Blender, MeshLab, trimesh and Open3D read them).
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", type=Path, help="run directory with a fitted template")
    parser.add_argument("--out", type=Path, required=True, help="mesh file: .ply, .glb or .obj")
    parser.add_argument("--edit", default=None, help="export the edit RUN/edits/NAME")
    parser.add_argument("--strength", type=float, default=1.0, help="edit strength (0..1)")
    parser.add_argument(
        "--normalized", action="store_true", help="keep run units instead of the capture's"
    )
    parser.add_argument(
        "--device", default="auto", choices=["auto", "cpu", "cuda"], help="torch device"
    )


def export_mesh(scene, out: Path, normalized: bool = False) -> dict:
    """Writes `scene`'s coloured mesh to `out` (capture units unless `normalized`), holding the
    lock of `out`: a second export to the same file is refused while this one runs."""
    from render.io import remove_partial_writes
    from render.locks import lock_entry
    from render.mesh_export import denormalize_points, save_colored_mesh

    with lock_entry(out, f"the mesh {out}"):
        remove_partial_writes(Path(out).parent, recursive=False, of=out)
        vertices, triangles, colors = scene.colored_mesh()
        units = "run"
        if not normalized:
            cams = scene.run.load_cameras()
            vertices = denormalize_points(vertices, cams.scale, cams.center, cams.rotation)
            units = "capture"
        save_colored_mesh(out, vertices, triangles, colors)
    return {"vertices": len(vertices), "triangles": len(triangles), "units": units}


def run(args: argparse.Namespace) -> int:
    from render.errors import SineError
    from render.mesh_export import MESH_SUFFIXES

    if args.out.suffix.lower() not in MESH_SUFFIXES:
        raise SineError(f"--out {args.out}: use a .ply, .glb or .obj file name")
    from recon.rundir import RunDir

    RunDir(args.run).refuse_output_inside(args.out)
    from edit.scene import load_scene

    scene = load_scene(args.run, args.edit, args.strength, args.device)
    stats = export_mesh(scene, args.out, args.normalized)
    print(
        f"export: {stats['vertices']} vertices, {stats['triangles']} triangles "
        f"({scene.name}, {stats['units']} units) -> {args.out}"
    )
    return 0
