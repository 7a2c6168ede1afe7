"""Times `sine synth` and checks its ground truth at full size; prints a table.

    .venv/bin/python bench/bench_synth.py [--views 36 --width 320 --height 240]

Rows: spot (../shared/data/meshes/spot, if present) and the procedural toycar, each with both GT
edits. Columns: seconds (load / render / write / total), worst distance of unprojected depth to
mesh.ply relative to the bbox diagonal, mask == depth > 0, fraction of mesh vertices projecting
into the (1-px dilated) mask, pixels changed outside the texture-edited part.
"""

from __future__ import annotations

import argparse
import json
import tempfile
import time
from pathlib import Path

import cv2
import numpy as np

from recon.synth import SynthConfig, synthesize
from render.cameras import load_cameras
from render.io import read_depth, read_label_map, read_mask

SPOT = Path(__file__).resolve().parents[1].parent / "shared/data/meshes/spot/spot_triangulated.obj"


def check(run: Path) -> dict:
    import open3d as o3d
    import trimesh

    mesh = trimesh.load(str(run / "mesh.ply"), process=False)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    diagonal = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    worst, mask_ok, inside = 0.0, True, []
    for cam in load_cameras(run / "cameras.json").frames:
        stem = Path(cam.name).stem
        depth = read_depth(run / "depth" / f"{stem}.npy")
        mask = read_mask(run / "masks" / f"{stem}.png")
        mask_ok &= bool(np.array_equal(mask, depth > 0))
        rows, cols = np.nonzero(depth > 0)
        z = depth[rows, cols].astype(np.float64)
        cam_pts = np.stack(
            [(cols + 0.5 - cam.cx) / cam.fx * z, (rows + 0.5 - cam.cy) / cam.fy * z, z], 1
        )
        world = cam_pts @ cam.camera_to_world[:3, :3].T + cam.camera_to_world[:3, 3]
        dist = scene.compute_distance(o3d.core.Tensor(world.astype(np.float32))).numpy()
        worst = max(worst, float(dist.max()) / diagonal)
        grown = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        uv, _ = cam.project(mesh.vertices)
        col = np.clip(np.floor(uv[:, 0]).astype(int), 0, cam.width - 1)
        row = np.clip(np.floor(uv[:, 1]).astype(int), 0, cam.height - 1)
        inside.append(grown[row, col].mean())
    return {"depth_err_rel": worst, "mask_eq_depth": mask_ok, "verts_in_mask": min(inside)}


def texture_leak(run: Path) -> int:
    edit = json.loads((run / "edits/texture/edit.json").read_text())
    leaked = 0
    for cam in load_cameras(run / "cameras.json").frames:
        stem = Path(cam.name).stem
        labels = read_label_map(run / "labels" / f"{stem}.png")
        a = cv2.imread(str(run / "images" / f"{stem}.png"))
        b = cv2.imread(str(run / "edits/texture/images" / f"{stem}.png"))
        leaked += int(np.any(a != b, axis=2)[labels != edit["part"]].sum())
    return leaked


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--views", type=int, default=36, help="views per turntable")
    parser.add_argument("--width", type=int, default=320, help="image width")
    parser.add_argument("--height", type=int, default=240, help="image height")
    args = parser.parse_args()
    sources = [("toycar", dict(procedural="toycar"))]
    if SPOT.is_file():
        sources.insert(0, ("spot", dict(mesh=SPOT)))
    header = (
        f"{'object':8} {'load':>6} {'render':>7} {'write':>6} {'total':>6} {'+2 edits':>8} "
        f"{'depth err/diag':>14} {'mask==d>0':>9} {'verts in mask':>13} {'tex leak px':>11}"
    )
    print(header)
    with tempfile.TemporaryDirectory() as tmp:
        for name, src in sources:
            common = dict(views=args.views, width=args.width, height=args.height, **src)
            t0 = time.perf_counter()
            s = synthesize(SynthConfig(out=Path(tmp) / name, **common), progress=False)
            total = time.perf_counter() - t0
            t1 = time.perf_counter()
            out = Path(tmp) / f"{name}_edits"
            synthesize(
                SynthConfig(out=out, edit=["geometric", "texture"], **common), progress=False
            )
            with_edits = time.perf_counter() - t1
            c = check(Path(tmp) / name)
            ce = check(out / "edits/geometric")
            print(
                f"{name:8} {s['seconds_load']:6.2f} {s['seconds_render']:7.2f} "
                f"{s['seconds_write']:6.2f} {total:6.2f} {with_edits:8.2f} "
                f"{max(c['depth_err_rel'], ce['depth_err_rel']):14.2e} "
                f"{str(c['mask_eq_depth'] and ce['mask_eq_depth']):>9} "
                f"{min(c['verts_in_mask'], ce['verts_in_mask']):13.4f} {texture_leak(out):11d}"
            )


if __name__ == "__main__":
    main()
