"""The geometric edit's shape prior M_P against ground truth, vertex by vertex, on the editing grid.

    python bench/bench_prior.py --out DIR [--objects toycar mug] [--edits vertical sideways]

Uses what `bench/bench_edit_geometry.py --out DIR` prepared: DIR/<object>/run with its fitted
template, the GT edit of each kind (DIR/<object>/synth for vertical, gt_<kind> for the others) and
a finished `<kind>_ours` edit whose template view, target and editable region are reused. The GT
edit is a known function of position, so every vertex of the template's proxy has a true edited
position; the table gives the prior's mean distance to it (run units) on the vertices the GT edit
moves by more than 0.01 ("moving"; the proxy itself scores the "no edit" row) and on the rest
("still", should stay 0), for each way of lifting the handles to 3D. Seconds; no GPU.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

# how the handles are lifted: name -> (upright plane, object axes, mirrored)
LIFTINGS = {
    "image plane (keep depth)": (False, False, False),
    "upright plane": (True, False, False),
    "object axes, else upright": (True, True, False),
    "upright plane, mirrored": (True, False, True),
    "object axes, mirrored": (True, True, True),
}


def prior_rows(work: Path, kind: str) -> list[tuple[str, float, float, float]]:
    import trimesh
    from bench_edit_geometry import gt_move

    from edit.shape_prior import build_prior_mesh, object_axes
    from recon.fit_proxy import template_proxy
    from recon.rundir import RunDir
    from render.io import read_image, read_json, read_mask
    from render.raycast import MeshRaycaster

    run = RunDir(work / "run")
    edit_dir = run.root / "edits" / f"{kind}_ours"
    cams = run.load_cameras()
    camera = cams.frames[read_json(edit_dir / "edit.json")["view"]]
    proxy = trimesh.load(template_proxy(run), force="mesh", process=False)
    vertices, triangles = np.asarray(proxy.vertices, np.float64), np.asarray(proxy.faces)
    move, _ = gt_move(run, work / ("synth" if kind == "vertical" else f"gt_{kind}"))
    truth = move(vertices)
    moving = np.linalg.norm(truth - vertices, axis=1) > 0.01
    depth = MeshRaycaster((vertices, triangles)).depth(camera)
    inputs = dict(
        template_rgb=read_image(edit_dir / "template_view.png"),
        template_alpha=read_mask(run.root / "masks" / camera.name).astype(np.float32),
        target_rgb=read_image(edit_dir / "target.png"),
        target_alpha=read_mask(edit_dir / "target_mask.png").astype(np.float32),
        region=read_mask(edit_dir / "region.png"),
    )
    rows = [("no edit (the proxy)", *_errors(vertices, truth, moving), 0.0)]
    for name, (upright, axes, mirrored) in LIFTINGS.items():
        t0 = time.perf_counter()
        try:
            prior = build_prior_mesh(
                camera,
                vertices,
                triangles,
                depth,
                **inputs,
                symmetric=mirrored,
                up=cams.up if upright else None,
                axes=object_axes(vertices, cams.up) if axes else None,
            )
        except Exception as e:  # noqa: BLE001 (no mirror plane: say so in the table)
            print(f"  {name}: {e}")
            continue
        rows.append((name, *_errors(prior.vertices, truth, moving), time.perf_counter() - t0))
    return rows


def _errors(points, truth, moving) -> tuple[float, float]:
    """Mean distance to the GT on moving vertices and on the still ones."""
    err = np.linalg.norm(points - truth, axis=1)
    return float(err[moving].mean()), float(err[~moving].mean())


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, required=True, help="bench_edit_geometry's --out folder")
    ap.add_argument("--objects", nargs="+", help="default: every object prepared in --out")
    ap.add_argument("--edits", nargs="+", default=["vertical", "sideways", "tilted", "scale_part"])
    args = ap.parse_args()
    objects = args.objects or sorted(p.parent.name for p in args.out.glob("*/run"))
    print("| object | edit | handles lifted into | moving | still | seconds |")
    print("|---|---|---|---:|---:|---:|")
    for obj in objects:
        for kind in args.edits:
            work = args.out / obj
            if not (work / "run" / "edits" / f"{kind}_ours" / "edit.json").is_file():
                continue
            for name, moving, still, seconds in prior_rows(work, kind):
                print(f"| {obj} | {kind} | {name} | {moving:.4f} | {still:.5f} | {seconds:.1f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
