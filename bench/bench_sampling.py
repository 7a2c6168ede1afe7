"""Proxy-band sampling vs the paper's uniform 64+128 sampling, same data, same iterations.

Builds a synthetic spot turntable (`sine synth`, 36 views; the GT mesh stands in for the proxy),
fits the template with each sampler in its own process (so peak memory is per variant), and
prints held-out PSNR/SSIM, training time, samples per ray and peak RSS as a table.

    .venv/bin/python bench/bench_sampling.py [--iterations 100] [--batch-rays 1024] [--threads 1]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see sine_cli.py

import argparse
import json
import resource
import shutil
import subprocess
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SPOT = ROOT.parent / "shared" / "data" / "meshes" / "spot" / "spot_triangulated.obj"


def make_run(work: Path, size: int, views: int) -> Path:
    from recon.synth import SynthConfig, synthesize

    synth = work / "synth"
    if not (synth / "cameras.json").is_file():
        synthesize(
            SynthConfig(out=synth, mesh=SPOT, views=views, width=size, height=size), progress=False
        )
    run = work / "run"
    if not run.is_dir():
        run.mkdir(parents=True)
        for name in ("images", "masks"):
            shutil.copytree(synth / name, run / name)
        shutil.copy(synth / "cameras.json", run / "cameras.json")
        shutil.copy(synth / "mesh.ply", run / "proxy_mesh.ply")
    return run


def worker(args) -> None:
    """One fit in this process; prints a JSON line."""
    from recon.fit import fit_template
    from recon.fit_config import FitConfig

    run = Path(args.work) / f"run_{args.worker}"
    if run.exists():
        shutil.rmtree(run)
    shutil.copytree(Path(args.work) / "run", run)
    cfg = FitConfig(
        sampler=args.worker,
        iterations=args.iterations,
        batch_rays=args.batch_rays,
        threads=args.threads,
        previews=0,
        checkpoint_every=10**9,
    )
    t0 = time.perf_counter()
    m = fit_template(run, cfg, progress=False)
    m["wall_seconds"] = time.perf_counter() - t0
    m["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print("RESULT " + json.dumps(m))


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--work", default="/tmp/sine_bench_sampling", help="scratch folder")
    ap.add_argument("--size", type=int, default=256, help="image width = height")
    ap.add_argument("--views", type=int, default=36, help="turntable views")
    ap.add_argument("--iterations", type=int, default=100, help="training steps (both samplers)")
    ap.add_argument("--batch-rays", type=int, default=1024, help="rays per step (both samplers)")
    ap.add_argument(
        "--threads", type=int, default=1, help="torch threads (1 is robust on a busy box)"
    )
    ap.add_argument("--eval-views", type=int, default=2, help="held-out views scored (0: all 5)")
    ap.add_argument("--samplers", nargs="+", default=["band", "uniform"], help="variants to run")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args)
        return
    if not SPOT.is_file():
        sys.exit(f"missing {SPOT}")
    work = Path(args.work)
    make_run(work, args.size, args.views)
    rows = []
    for sampler in args.samplers:
        cmd = [
            sys.executable,
            __file__,
            "--worker",
            sampler,
            "--work",
            str(work),
            "--iterations",
            str(args.iterations),
            "--batch-rays",
            str(args.batch_rays),
            "--threads",
            str(args.threads),
        ]
        out = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT)
        line = [x for x in out.stdout.splitlines() if x.startswith("RESULT ")]
        if not line:
            sys.exit(f"{sampler} failed:\n{out.stderr[-3000:]}")
        rows.append((sampler, json.loads(line[0][7:])))
    print(
        f"spot {args.size}x{args.size}, {args.views} views, {args.iterations} steps x "
        f"{args.batch_rays} rays, {args.threads} thread(s)"
    )
    print("PSNR: whole held-out image; fg PSNR: the object's mask pixels only")
    hdr = (
        f"{'sampler':<8} {'PSNR':>6} {'fg PSNR':>7} {'SSIM':>6} {'train s':>8} {'s/step':>7} "
        f"{'eval s':>7} {'samples/ray':>11} {'field rays':>10} {'peak MB':>8}"
    )
    print(hdr)
    for name, m in rows:
        print(
            f"{name:<8} {m['heldout_psnr']:>6.2f} {m.get('heldout_psnr_object', 0):>7.2f} "
            f"{m['heldout_ssim']:>6.3f} {m['train_seconds']:>8.1f} "
            f"{m['train_seconds'] / m['iterations']:>7.3f} {m['eval_seconds']:>7.1f} "
            f"{m['samples_per_ray']:>11} {m['train_rays_needing_field']:>10} {m['peak_rss_mb']:>8.0f}"
        )
    if len(rows) == 2:
        (_, a), (_, b) = rows
        print(
            f"training speed-up of {rows[0][0]} over {rows[1][0]} (same steps): "
            f"{b['train_seconds'] / a['train_seconds']:.1f}x; PSNR difference "
            f"{a['heldout_psnr'] - b['heldout_psnr']:+.2f} dB (fg "
            f"{a.get('heldout_psnr_object', 0) - b.get('heldout_psnr_object', 0):+.2f} dB)"
        )


if __name__ == "__main__":
    main()
