"""Reconstruction benchmark: camera accuracy against ground truth + the run reports.

    .venv/bin/python bench/bench_recon.py RUN --gt-par ../shared/data/middlebury-templeSparseRing/templeSR_par.txt
    .venv/bin/python bench/bench_recon.py RUN --gt-cameras CAPTURE/cameras.json --gt-mesh CAPTURE/mesh.ply
    .venv/bin/python bench/bench_recon.py --variants /tmp/bench_recon [--datasets spot temple dino]

The first two forms score one finished run. `--variants OUT` runs `sine recon` (library call)
on each dataset with each variant of the SfM/depth/turntable options into
OUT/<dataset>-<variant> and prints one table: pose source, registered views, median rotation /
centre error, proxy Chamfer-L1 (spot), the self-check's hull IoU, silhouette IoU, verdict,
watertightness and seconds, variants side by side (a run the self-check stopped is scored from
what it wrote: verdict STOPPED).

    .venv/bin/python bench/bench_recon.py --variants /tmp/bt --datasets toycar figurine dinoSR \
        temple --which turntable=off turntable=auto

Aligns the recon's camera centres to the ground truth by a similarity (Umeyama), then prints
per-view and median rotation error (degrees) and camera-centre error (% of the ring radius =
mean distance of the GT centres to their centroid); with --gt-mesh also the proxy mesh's
Chamfer-L1 to the GT mesh (in GT units and in % of the GT bbox diagonal) after that alignment,
plus the run's recon_report.json numbers and per-stage seconds.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from render.cameras import Camera, camera_from_krt, load_cameras, read_middlebury_par  # noqa: E402
from render.io import read_json  # noqa: E402


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """Similarity (s, R, t) minimising sum |s R src_i + t - dst_i|^2 (src, dst [N, 3])."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var_s = (xs**2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var_s)
    t = mu_d - s * R @ mu_s
    return s, R, t


def camera_errors(est: list[Camera], gt: list[Camera]) -> dict:
    """Per-view errors after aligning `est` centres to `gt` centres (matched by order)."""
    c_est = np.array([c.center for c in est])
    c_gt = np.array([c.center for c in gt])
    s, R, t = umeyama(c_est, c_gt)
    radius = float(np.linalg.norm(c_gt - c_gt.mean(0), axis=1).mean())
    centre_err = np.linalg.norm((s * c_est @ R.T + t) - c_gt, axis=1) / radius * 100.0
    rot_err = []
    for e, g in zip(est, gt, strict=True):
        r_aligned = R @ e.camera_to_world[:3, :3]  # camera-to-world rotation in the GT frame
        rel = r_aligned.T @ g.camera_to_world[:3, :3]
        rot_err.append(np.degrees(np.arccos(np.clip((np.trace(rel) - 1) / 2, -1, 1))))
    return {
        "scale": s,
        "R": R,
        "t": t,
        "radius": radius,
        "rotation_error_deg": np.array(rot_err),
        "centre_error_pct": centre_err,
    }


def chamfer_l1(a: np.ndarray, b: np.ndarray) -> float:
    """Symmetric Chamfer-L1: mean of the two mean nearest-neighbour distances."""
    from scipy.spatial import cKDTree

    d_ab = cKDTree(b).query(a)[0]
    d_ba = cKDTree(a).query(b)[0]
    return float(0.5 * (d_ab.mean() + d_ba.mean()))


def sample_mesh(path: Path, n: int = 100_000, seed: int = 0) -> np.ndarray:
    import open3d as o3d

    o3d.utility.random.seed(seed)
    mesh = o3d.io.read_triangle_mesh(str(path))
    return np.asarray(mesh.sample_points_uniformly(n).points)


DATA = Path(__file__).resolve().parents[2] / "shared" / "data"

# name -> (ReconConfig overrides, IngestConfig overrides); "default" = the shipped defaults.
BEFORE = {
    "sfm_min_object_px": 0.0,
    "sfm_final_ba": False,
    "sfm_peak_threshold": 0.004,
    "sfm_threads": -1,
}
UPSCALE = {**BEFORE, "sfm_min_object_px": 400.0}
PEAK = {**UPSCALE, "sfm_peak_threshold": 0.002, "sfm_threads": 1}
VARIANTS = {
    "before": (BEFORE, {"ignore_intrinsics": True}),
    "+intrinsics": (BEFORE, {}),
    "+upscale": (UPSCALE, {}),
    "+peak.002,1thread": (PEAK, {}),
    "+final_ba=default": ({}, {}),
    "default-intrinsics": ({}, {"ignore_intrinsics": True}),
    "+dsp": ({"sfm_domain_size_pooling": True}, {}),
    "+guided": ({"sfm_guided_matching": True}, {}),
    "default": ({}, {}),
    "hull": ({"depth_method": "visual_hull"}, {}),
    "hull+stereo": ({"depth_method": "visual_hull+stereo"}, {}),
    "turntable=off": ({"turntable": "off", "accept_poor_poses": True}, {}),
    "turntable=auto": ({"turntable": "auto"}, {}),
    "turntable=on": ({"turntable": "on"}, {}),
}
DEPTH_VARIANTS = ("default", "hull", "hull+stereo")  # the ones that apply with known poses


def datasets(out: Path) -> dict:
    """name -> (capture, ignore_poses, GT cameras loader or None, GT mesh or None)."""
    spot = out / "spot320"
    if not (spot / "transforms.json").is_file():
        from recon.synth import SynthConfig, synthesize

        mesh = DATA / "meshes" / "spot" / "spot_triangulated.obj"
        synthesize(SynthConfig(mesh=mesh, out=spot, views=36, width=320, height=240))
    temple_par = DATA / "middlebury-templeSparseRing" / "templeSR_par.txt"
    dino_par = DATA / "middlebury-dinoSparseRing" / "dinoSR_par.txt"
    toys = {}
    for name in ("toycar", "figurine"):
        cap = out / f"{name}160"
        if not (cap / "transforms.json").is_file():
            from recon.synth import SynthConfig, synthesize

            synthesize(SynthConfig(procedural=name, out=cap, views=36, width=160, height=160))
        toys[name] = (cap, True, lambda cap=cap: _gt_cameras(cap / "cameras.json"), None)
    return {
        **toys,
        "dinoSR": (dino_par.parent, True, lambda: _gt_par(dino_par), None),
        "spot": (spot, True, lambda: _gt_cameras(spot / "cameras.json"), spot / "mesh.ply"),
        "spot_known": (spot, False, lambda: _gt_cameras(spot / "cameras.json"), spot / "mesh.ply"),
        "temple": (temple_par.parent, True, lambda: _gt_par(temple_par), None),
        "dino": (DATA / "oxford-dinosaur" / "images", False, None, None),
    }


def _gt_cameras(path: Path) -> dict:
    return {Path(c.name).stem: c for c in load_cameras(path).frames}


def _gt_par(path: Path) -> dict:
    return {
        Path(name).stem: camera_from_krt(K, R, t, 640, 480, name)
        for name, K, R, t in read_middlebury_par(path)
    }


def score_run(run: Path, gt_by_name: dict | None, gt_mesh: Path | None) -> dict:
    """Camera errors (median), Chamfer (% bbox diagonal) and report numbers of one run."""
    report = read_json(run / "recon_report.json")
    row = {
        "registered": f"{report.get('registered_views')}/{report.get('total_views')}",
        "rot_med": None,
        "ctr_med": None,
        "chamfer_pct": None,
        "iou": report.get("silhouette_iou_mean"),
        "watertight": report.get("proxy_watertight"),
        "reproj": report.get("mean_reprojection_error_px"),
        "depth": report.get("depth_source"),
        "s_poses": report.get("seconds_poses"),
        "s_total": report.get("seconds_total_before_report"),
        "verdict": report.get("verdict"),
        "pose_source": report.get("pose_source"),
        "hull_iou": (report.get("self_check_poses") or {}).get("hull_iou_mean"),
    }
    if gt_by_name:
        est_by_name = {Path(c.name).stem: c for c in load_cameras(run / "cameras.json").frames}
        common = [k for k in est_by_name if k in gt_by_name]
        err = camera_errors([est_by_name[k] for k in common], [gt_by_name[k] for k in common])
        row["rot_med"] = float(np.median(err["rotation_error_deg"]))
        row["ctr_med"] = float(np.median(err["centre_error_pct"]))
        if gt_mesh is not None:
            gt_points = sample_mesh(gt_mesh)
            proxy = sample_mesh(run / "proxy_mesh.ply")
            aligned = err["scale"] * proxy @ err["R"].T + err["t"]
            diag = float(np.linalg.norm(gt_points.max(0) - gt_points.min(0)))
            row["chamfer_pct"] = 100 * chamfer_l1(aligned, gt_points) / diag
    return row


def run_variants(out: Path, names: list[str], variants: list[str]) -> int:
    from recon.ingest import IngestConfig
    from recon.pipeline import run_recon
    from recon.recon_config import ReconConfig
    from recon.rundir import RunDir

    out.mkdir(parents=True, exist_ok=True)
    sets = datasets(out)
    rows = []
    for name in names:
        capture, ignore_poses, gt, gt_mesh = sets[name]
        for variant in variants:
            if not ignore_poses and variant not in DEPTH_VARIANTS and name != "dino":
                continue  # known poses: the SfM variants do not apply
            recon_over, ingest_over = VARIANTS[variant]
            cfg = ReconConfig(**recon_over)
            icfg = IngestConfig(ignore_poses=ignore_poses, force=True, **ingest_over)
            run = out / f"{name}-{variant}"
            try:
                run_recon(capture, RunDir(run), cfg, icfg)
                row = score_run(run, gt() if gt else None, gt_mesh)
            except Exception as exc:  # noqa: BLE001 - a failed variant is a table row
                row = {"registered": f"FAILED: {exc}"[:60]}
                if (run / "recon_report.json").is_file() and (run / "cameras.json").is_file():
                    row = {**score_run(run, gt() if gt else None, None), "verdict": "STOPPED"}
            rows.append({"dataset": name, "variant": variant, **row})
            print(rows[-1], flush=True)
    cols = ["dataset", "variant", "pose_source", "registered", "rot_med", "ctr_med",
            "chamfer_pct", "hull_iou", "iou", "verdict", "watertight", "reproj", "depth",
            "s_poses", "s_total"]  # fmt: skip
    print("| " + " | ".join(cols) + " |")
    print("|" + "---|" * len(cols))
    for row in rows:
        cells = []
        for c in cols:
            v = row.get(c)
            cells.append("-" if v is None else f"{v:.3f}" if isinstance(v, float) else str(v))
        print("| " + " | ".join(cells) + " |")
    return 0


def main() -> int:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("run", type=Path, nargs="?", help="run directory written by `sine recon`")
    parser.add_argument("--variants", type=Path, help="run the variant table into this folder")
    parser.add_argument(
        "--datasets",
        nargs="+",
        default=["spot", "spot_known", "temple", "dino"],
        help="datasets of the variant table (spot, spot_known, temple, dino = oxford-dinosaur, "
        "dinoSR = middlebury-dinoSparseRing, toycar, figurine = procedural 36 x 160 px)",
    )
    parser.add_argument(
        "--which", nargs="+", default=list(VARIANTS), help="variants to run (see VARIANTS)"
    )
    parser.add_argument("--gt-par", type=Path, help="Middlebury *_par.txt with the GT cameras")
    parser.add_argument(
        "--gt-cameras", type=Path, help="cameras.json with the GT cameras (e.g. from `sine synth`)"
    )
    parser.add_argument(
        "--gt-mesh", type=Path, help="GT mesh in the GT cameras' frame (Chamfer-L1)"
    )
    args = parser.parse_args()
    if args.variants:
        return run_variants(args.variants, args.datasets, args.which)
    if args.run is None:
        parser.error("give a RUN directory or --variants OUT")

    cams = load_cameras(args.run / "cameras.json")
    est_by_name = {Path(c.name).stem: c for c in cams.frames}
    if args.gt_par:
        gt_by_name = {
            Path(name).stem: camera_from_krt(K, R, t, 640, 480, name)
            for name, K, R, t in read_middlebury_par(args.gt_par)
        }
    elif args.gt_cameras:
        gt_by_name = {Path(c.name).stem: c for c in load_cameras(args.gt_cameras).frames}
    else:
        parser.error("give --gt-par or --gt-cameras")
    common = [k for k in est_by_name if k in gt_by_name]
    est = [est_by_name[k] for k in common]
    gt = [gt_by_name[k] for k in common]
    err = camera_errors(est, gt)

    print(f"{'view':<16}{'rot err (deg)':>15}{'centre err (% radius)':>24}")
    for k, r, c in zip(common, err["rotation_error_deg"], err["centre_error_pct"], strict=True):
        print(f"{k:<16}{r:>15.3f}{c:>24.3f}")
    print(
        f"{'median':<16}{np.median(err['rotation_error_deg']):>15.3f}{np.median(err['centre_error_pct']):>24.3f}"
    )
    print(
        f"{'max':<16}{err['rotation_error_deg'].max():>15.3f}{err['centre_error_pct'].max():>24.3f}"
    )
    print(f"registered views compared: {len(common)} of {len(gt_by_name)} GT views")

    if args.gt_mesh:
        proxy = sample_mesh(args.run / "proxy_mesh.ply")  # run units
        gt_points = sample_mesh(args.gt_mesh)
        # run cameras -> GT frame: x_gt = s R x_run + t (the camera similarity).
        aligned = err["scale"] * proxy @ err["R"].T + err["t"]
        lo, hi = gt_points.min(0), gt_points.max(0)
        diag = float(np.linalg.norm(hi - lo))
        cd = chamfer_l1(aligned, gt_points)
        print(
            f"proxy mesh Chamfer-L1 to GT: {cd:.5f} GT units = {100 * cd / diag:.3f} % of bbox diagonal"
        )

    report_path = args.run / "recon_report.json"
    if report_path.is_file():
        report = read_json(report_path)
        print("recon_report.json:")
        for key, value in report.items():
            if not isinstance(value, (list, dict)):
                print(f"  {key:<36}{value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
