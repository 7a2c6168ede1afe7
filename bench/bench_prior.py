"""The geometric edit's shape prior M_P against ground truth, vertex by vertex.

    python bench/bench_prior.py --out bench/out/edit_geometry [--objects toycar figurine spot]

Uses the objects `bench/bench_edit_geometry.py --out DIR` prepared (DIR/<object>/synth with its
GT geometric edit, DIR/<object>/run with a fitted template and a finished `ours` edit, whose
template view, target and editable region are reused). The GT edit is a known function of
position (`recon.synth.stretch_displacement`), so every proxy vertex has a true edited position;
the table gives the prior's mean distance to it (run units) on the vertices the GT edit moves by
more than 0.01 ("moving"; the proxy itself scores the "no edit" row), on the prior's handles,
and on the rest (should stay 0), for each way of lifting the handles. Prints one table; no GPU.
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


def gt_positions(work: Path, vertices: np.ndarray) -> np.ndarray:
    """Proxy vertices [V, 3] (run units) -> where the GT edit takes them [V, 3] (run units)."""
    from recon.normalize import Normalization
    from recon.rundir import RunDir
    from recon.synth import stretch_displacement
    from render.io import read_json
    from render.mesh_export import denormalize_points

    cams = RunDir(work / "run").load_cameras()
    to_run = Normalization(cams.scale, cams.center, cams.rotation)  # synth units -> run units
    edit = read_json(work / "synth" / "edits" / "geometric" / "edit.json")
    synth = denormalize_points(vertices, cams.scale, cams.center, cams.rotation)
    moved = synth + stretch_displacement(synth, edit["plane"], edit["scale"], edit["falloff"])
    return to_run.apply_points(moved)


def prior_rows(work: Path) -> list[tuple[str, float, float, float, float]]:
    import trimesh

    from edit.shape_prior import build_prior_mesh
    from recon.rundir import RunDir
    from render.io import read_image, read_json, read_mask
    from render.raycast import MeshRaycaster

    run = RunDir(work / "run")
    edit_dir = work / "run" / "edits" / "ours"
    cams = run.load_cameras()
    camera = cams.frames[read_json(edit_dir / "edit.json")["view"]]
    proxy = trimesh.load(work / "run" / "proxy_mesh.ply", process=False)
    vertices, triangles = np.asarray(proxy.vertices, np.float64), np.asarray(proxy.faces)
    truth = gt_positions(work, vertices)
    moving = np.linalg.norm(truth - vertices, axis=1) > 0.01
    depth = MeshRaycaster((vertices, triangles)).depth(camera)
    inputs = dict(
        template_rgb=read_image(edit_dir / "template_view.png"),
        template_alpha=read_mask(work / "run" / "masks" / camera.name).astype(np.float32),
        target_rgb=read_image(edit_dir / "target.png"),
        target_alpha=read_mask(edit_dir / "target_mask.png").astype(np.float32),
        region=read_mask(edit_dir / "region.png"),
    )
    rows = [("no edit (the proxy)", *_errors(vertices, truth, moving, np.zeros(0, int)), 0.0)]
    for name, up in (("image plane (keep depth)", None), ("upright plane", cams.up)):
        t0 = time.perf_counter()
        prior = build_prior_mesh(camera, vertices, triangles, depth, **inputs, up=up)
        errors = _errors(prior.vertices, truth, moving, prior.handle_ids)
        rows.append((name, *errors, time.perf_counter() - t0))
    return rows


def _errors(points, truth, moving, handles) -> tuple[float, float, float]:
    """Mean distance to the GT on moving vertices, on the handles, and on the still ones."""
    err = np.linalg.norm(points - truth, axis=1)
    on_handles = float(err[handles].mean()) if len(handles) else float("nan")
    return float(err[moving].mean()), on_handles, float(err[~moving].mean())


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, required=True, help="bench_edit_geometry's --out folder")
    ap.add_argument("--objects", nargs="+", default=["toycar", "figurine", "spot"])
    args = ap.parse_args()
    print("| object | handles lifted into | moving | handles | still | seconds |")
    print("|---|---|---:|---:|---:|---:|")
    for obj in args.objects:
        work = args.out / obj
        if not (work / "run" / "edits" / "ours" / "edit.json").is_file():
            print(f"{obj}: no finished `ours` edit in {work}; run bench_edit_geometry.py first")
            continue
        for name, moving, handles, still, seconds in prior_rows(work):
            print(
                f"| {obj} | {name} | {moving:.4f} | {handles:.4f} | {still:.5f} | {seconds:.1f} |"
            )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
