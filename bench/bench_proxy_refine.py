"""Proxy refine loop: the proxy re-fused from the fitted template's depth, before/after.

    .venv/bin/python bench/bench_proxy_refine.py --out /tmp/bpr [--cases spot dinosaur] \
        [--spot-capture DIR] [--dino-run DIR] [--iterations 400] \
        [--variant half:refine_scale=0.5 --variant full:refine_scale=1.0,refine_carve=0]

Cases (each prepared once under --out/CASE and reused):
  spot      `sine synth` of the shared spot mesh (36 views, 256x256; or --spot-capture, an
            existing one, read only) -> `sine recon --depth-method visual_hull+stereo` (the
            dataset depth is not used) -> `sine fit --iterations N`
  dinosaur  a copy of --dino-run (a finished `sine recon` of oxford-dinosaur), fitted with
            `sine fit --iterations N` when its template is missing or from an older version

Each variant is a set of `recon.proxy_refine.RefineConfig` options; `refine_run` (the run's
training views, masks, proxy settings) makes the new proxy in-process; it is written to
--out/CASE/proxy_VARIANT.ply (the run's proxy_mesh.ply is left alone). The table: silhouette IoU
with the masks (mean over the training views) before/after, with a ground-truth mesh (spot: the
capture's mesh.ply in run units via cameras.json's normalisation) the symmetric Chamfer-L1 (mean
of the two mean nearest-neighbour distances of 100k surface samples, run units) with its two
sides (accuracy: proxy -> GT, completeness: GT -> proxy), triangles, seconds. Timings taken on a
shared machine are indicative only.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see sine_cli.py

import argparse
import json
import shutil
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))
SHARED = ROOT.parent / "shared" / "data"
SINE = [sys.executable, "-m", "sine_cli"]


def sine(*args: str) -> None:
    print("$ sine", " ".join(args), flush=True)
    subprocess.run([*SINE, *args], check=True, cwd=ROOT)


def needs_fit(run: Path) -> bool:
    """True when the run has no template the current code loads."""
    from recon.fit import load_fitted
    from render.errors import SineError

    try:
        load_fitted(run)
    except (SineError, KeyError, RuntimeError):
        return True
    return False


def prepare_spot(out: Path, capture: Path | None, iterations: int) -> tuple[Path, Path]:
    """(run, capture) of the spot case: synth, recon without dataset depth, fit."""
    capture = capture or out / "spot" / "synth"
    if not (capture / "cameras.json").is_file():
        mesh = SHARED / "meshes" / "spot" / "spot_triangulated.obj"
        sine("synth", "--mesh", str(mesh), "--views", "36", "--width", "256", "--height",
             "256", "--quiet", "--out", str(capture))  # fmt: skip
    run = out / "spot" / "run"
    if not (run / "proxy_mesh.ply").is_file():
        sine("recon", str(capture), "--out", str(run), "--depth-method", "visual_hull+stereo")
    if needs_fit(run):
        sine("fit", str(run), "--iterations", str(iterations), "--quiet")
    return run, capture


def prepare_dino(out: Path, source: Path, iterations: int) -> Path:
    run = out / "dinosaur" / "run"
    if not run.is_dir():
        shutil.copytree(source, run, ignore=shutil.ignore_patterns("edits", "sfm"))
    if needs_fit(run):
        shutil.rmtree(run / "template", ignore_errors=True)
        shutil.rmtree(run / "template.partial", ignore_errors=True)
        sine("fit", str(run), "--iterations", str(iterations), "--quiet")
    return run


def gt_points(capture: Path, run: Path, n: int = 100_000) -> np.ndarray:
    """The capture's mesh.ply sampled and mapped into run units (x_run = s R (x - c))."""
    import open3d as o3d

    from render.cameras import load_cameras

    cams = load_cameras(run / "cameras.json")
    o3d.utility.random.seed(0)
    pts = np.asarray(
        o3d.io.read_triangle_mesh(str(capture / "mesh.ply")).sample_points_uniformly(n).points
    )
    return cams.scale * (pts - cams.center) @ np.asarray(cams.rotation).T


def chamfer(mesh, gt: np.ndarray, n: int = 100_000) -> dict:
    """Symmetric Chamfer-L1 of mesh surface samples vs GT points, with its two sides."""
    import open3d as o3d
    from scipy.spatial import cKDTree

    o3d.utility.random.seed(0)
    pts = np.asarray(mesh.sample_points_uniformly(n).points)
    acc = cKDTree(gt).query(pts)[0].mean()
    comp = cKDTree(pts).query(gt)[0].mean()
    return {"chamfer": 0.5 * (acc + comp), "accuracy": acc, "completeness": comp}


def parse_variant(text: str) -> tuple[str, dict]:
    from recon.proxy_refine import RefineConfig

    name, _, body = text.partition(":")
    kinds = {k: type(v) for k, v in vars(RefineConfig()).items()}
    options = {}
    for item in filter(None, body.split(",")):
        key, _, value = item.partition("=")
        if key not in kinds:
            raise SystemExit(f"unknown refine option {key!r}; one of {sorted(kinds)}")
        kind = kinds[key]
        options[key] = (value not in ("0", "false", "False")) if kind is bool else kind(value)
    return name, options


def refine_case(case: str, run: Path, capture: Path | None, variants, out: Path) -> list[dict]:
    import open3d as o3d
    import torch

    from recon.fit import load_fitted
    from recon.fit_proxy import make_sampler
    from recon.proxy_mesh import write_mesh
    from recon.proxy_refine import RefineConfig, refine_run
    from recon.rundir import RunDir

    torch.set_num_threads(int(os.environ.get("THREADS", "1")))
    rd = RunDir(run)
    field, _, fit_cfg = load_fitted(run)
    sampler = make_sampler(fit_cfg, rd)
    gt = gt_points(capture, run) if capture is not None else None
    old = o3d.io.read_triangle_mesh(str(rd.proxy_mesh))
    rows = []
    for name, options in variants:
        t0 = time.perf_counter()
        mesh, stats = refine_run(rd, field, sampler, RefineConfig(**options))
        wall = time.perf_counter() - t0
        write_mesh(out / case / f"proxy_{name}.ply", mesh)
        row = {"case": case, "variant": name, "options": options, **stats, "wall_seconds": wall}
        if gt is not None:
            row.update({f"{k}_before": v for k, v in chamfer(old, gt).items()})
            row.update({f"{k}_after": v for k, v in chamfer(mesh, gt).items()})
        rows.append(row)
        print(json.dumps({k: v for k, v in row.items()}, default=float), flush=True)
    return rows


def fmt(value, digits: int = 4) -> str:
    if value is None:
        return "-"
    if isinstance(value, float):
        return f"{value:.{digits}f}"
    return str(value)


def table(rows: list[dict]) -> str:
    cols = [
        ("case", "case", 0),
        ("variant", "variant", 0),
        ("chamfer_before", "Chamfer before", 4),
        ("chamfer_after", "Chamfer after", 4),
        ("accuracy_before", "acc before", 4),
        ("accuracy_after", "acc after", 4),
        ("completeness_before", "comp before", 4),
        ("completeness_after", "comp after", 4),
        ("silhouette_iou_before", "IoU before", 4),
        ("silhouette_iou_after", "IoU after", 4),
        ("proxy_triangles_after", "triangles", 0),
        ("refine_voxel_size", "voxel", 4),
        ("refine_shift_median", "|shift| med", 4),
        ("seconds_render", "render s", 1),
        ("seconds_fuse", "fuse s", 1),
    ]
    lines = ["| " + " | ".join(title for _, title, _ in cols) + " |"]
    lines.append("|" + "---|" * len(cols))
    for row in rows:
        lines.append("| " + " | ".join(fmt(row.get(k), d) for k, _, d in cols) + " |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--cases", nargs="+", default=["spot"], choices=["spot", "dinosaur"])
    parser.add_argument("--spot-capture", type=Path, default=None)
    parser.add_argument("--dino-run", type=Path, default=Path("/work/dev/dino_run"))
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument(
        "--variant",
        action="append",
        default=None,
        help="NAME:key=value,... (RefineConfig options); default: half-size, all views",
    )
    args = parser.parse_args()
    variants = [parse_variant(v) for v in (args.variant or ["default:"])]
    args.out.mkdir(parents=True, exist_ok=True)
    rows = []
    for case in args.cases:
        if case == "spot":
            run, capture = prepare_spot(args.out, args.spot_capture, args.iterations)
        else:
            run, capture = prepare_dino(args.out, args.dino_run, args.iterations), None
        rows += refine_case(case, run, capture, variants, args.out)
    results = args.out / "results.json"
    old = json.loads(results.read_text()) if results.is_file() else []
    keep = [
        r for r in old if (r["case"], r["variant"]) not in {(x["case"], x["variant"]) for x in rows}
    ]
    results.write_text(json.dumps(keep + rows, indent=1, default=float))
    print(table(rows))


if __name__ == "__main__":
    main()
