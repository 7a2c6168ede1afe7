"""Template fidelity and fit throughput: `sine fit` variants side by side on the same runs.

Cases (each reconstructed once into --out/CASE/run the way a user would, then reused):
  spot      `sine synth` of the shared spot mesh (36 views 256x256) -> `sine recon` (known poses)
  toycar    `sine synth --procedural toycar` (36 x 256x256) -> `sine recon`
  figurine  `sine synth --procedural figurine` (36 x 256x256) -> `sine recon`
  dinosaur  `sine recon` of ../shared/data/oxford-dinosaur (SfM; ~2 min the first time)
  temple    `sine recon` of ../shared/data/middlebury-templeSparseRing (known poses)
  avocado   `sine synth` of the shared avocado mesh (36 x 256x256) -> `sine recon`
  a mesh file (OBJ/GLB/GLTF/PLY)   `sine synth --mesh` of it (36 x 256x256) -> `sine recon`
  a capture folder (photos, transforms.json, COLMAP, a calibrated ring)   `sine recon` of it
  (both named by their file or folder name)

Each variant is a set of `sine fit` options (`--variant NAME:key=value,key=value`; `native=0`
runs the torch hash-grid path instead of the C++ kernels; `code=DIR` imports the project from
DIR, e.g. a `git worktree` of an older commit, for a before/after on the same machine) fitted in
its own process (so peak memory is per variant) into its own copy of the run. The table gives held-out PSNR on object
pixels (the headline; masks from the capture) and over the whole image, SSIM, train seconds,
rays/s, samples/ray, samples/s and peak RSS; `--out/results.json` keeps every number and
`--out/CASE_VARIANT.png` a held-out view (render | truth).

    .venv/bin/python bench/bench_fit.py --out bench/out/fit --cases spot \
        --variant before:native=0 --variant after:
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

from bench_objects import case_name, synth_source

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared" / "data"
SINE = [sys.executable, "-m", "sine_cli"]


CAPTURES = {
    "dinosaur": SHARED / "oxford-dinosaur",
    "temple": SHARED / "middlebury-templeSparseRing",
}


def synth_case(case: str) -> list[str]:
    """`sine synth` arguments of a synthetic case (a built-in object or a mesh file)."""
    common = ["--views", "36", "--width", "256", "--height", "256", "--quiet"]
    source = synth_source(case)
    if "mesh" in source:
        return ["--mesh", str(source["mesh"]), *common]
    return ["--procedural", source["procedural"], *common]


def case_label(case: str) -> str:
    """The case's name in tables and folders (a capture folder's or a mesh file's name)."""
    return Path(case).name if Path(case).is_dir() else case_name(case)


def prepare(case: str, out: Path) -> Path:
    """The case's reconstructed run (made once)."""
    run = out / case_label(case) / "run"
    if (run / "proxy_mesh.ply").is_file():
        return run
    if case in CAPTURES:
        capture = CAPTURES[case]
    elif Path(case).is_dir():
        capture = Path(case).resolve()
    else:  # a shared mesh, a mesh file or a procedural object (`sine synth` names the known ones)
        capture = out / case_label(case) / "synth"
        cmd = [*SINE, "synth", "--out", str(capture), *synth_case(case)]
        if subprocess.run(cmd, cwd=ROOT).returncode:
            sys.exit(f"case {case!r}: not a built-in case, a mesh file or a capture folder")
    subprocess.run([*SINE, "recon", str(capture), "--out", str(run)], check=True, cwd=ROOT)
    return run


def parse_variant(spec: str) -> tuple[str, dict[str, str]]:
    name, _, opts = spec.partition(":")
    pairs = [p.split("=", 1) for p in opts.split(",") if p]
    return name, {k.strip(): v.strip() for k, v in pairs}


def worker(run: Path, opts: dict[str, str], preview: Path) -> None:
    """One fit in this process (a fresh copy of the run); prints a RESULT line."""
    from dataclasses import fields

    if "code" in opts:  # another checkout of the project (e.g. the commit before a change)
        sys.path.insert(0, str(Path(opts["code"]).resolve()))

    import numpy as np

    from recon.fit import fit_template
    from recon.fit_config import FitConfig

    types = {f.name: f.type for f in fields(FitConfig)}
    kwargs = {}
    for key, value in opts.items():
        if key in ("native", "code"):
            continue
        kind = str(types[key]).replace(" | None", "")  # annotations are strings here
        kwargs[key] = {"int": int, "float": float, "bool": lambda v: v in ("1", "true")}.get(
            kind, str
        )(value)
    cfg = FitConfig(**kwargs, checkpoint_every=10**9, checkpoint_seconds=10**9, previews=1)
    t0 = time.perf_counter()
    m = fit_template(run, cfg, progress=False, force=True)
    m["wall_seconds"] = time.perf_counter() - t0
    m["peak_rss_mb"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    shots = sorted((run / "template" / "previews").glob("*.png"))
    if shots:
        shutil.copy(shots[0], preview)
    m = {k: v for k, v in m.items() if isinstance(v, int | float | str | bool) or v is None}
    if "heldout_psnr_foreground" in m:  # older checkouts' name of the object PSNR
        m["heldout_psnr_object"] = m.pop("heldout_psnr_foreground")
    m.setdefault("samples_per_second", m["rays_per_second"] * m["samples_per_ray"])
    print("RESULT " + json.dumps(m, default=lambda v: float(np.asarray(v))))


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", default="bench/out/fit", help="work and results folder")
    ap.add_argument(
        "--cases",
        default="spot",
        help="comma-separated cases (see above): built-in names, mesh files, capture folders",
    )
    ap.add_argument(
        "--keep", action="store_true", help="keep each variant's run (CASE/run_NAME) to look at"
    )
    ap.add_argument(
        "--variant",
        action="append",
        default=None,
        help="NAME:key=value,... fit options of one variant (repeatable; default: defaults)",
    )
    ap.add_argument("--worker", nargs=3, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        run, opts, preview = args.worker
        worker(Path(run), json.loads(opts), Path(preview))
        return
    out = Path(args.out).resolve()
    variants = [parse_variant(v) for v in (args.variant or ["defaults:"])]
    results_path = out / "results.json"
    results = json.loads(results_path.read_text()) if results_path.is_file() else {"cases": []}
    rows = []
    for source in args.cases.split(","):
        base, case = prepare(source, out), case_label(source)
        for name, opts in variants:
            run = out / case / f"run_{name}"
            if run.exists():
                shutil.rmtree(run)
            shutil.copytree(base, run, ignore=shutil.ignore_patterns("template*", "edits"))
            env = dict(os.environ, SINE_NATIVE=opts.get("native", "1"))
            preview = out / f"{case}_{name}.png"
            cmd = [sys.executable, __file__, "--worker", str(run), json.dumps(opts), str(preview)]
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=ROOT, env=env)
            line = [x for x in proc.stdout.splitlines() if x.startswith("RESULT ")]
            if not line:
                sys.exit(f"{case}/{name} failed:\n{proc.stderr[-3000:]}")
            m = json.loads(line[0][7:])
            row = {"case": case, "variant": name, "options": opts, **m}
            rows.append(row)
            results["cases"] = [
                r for r in results["cases"] if (r["case"], r["variant"]) != (case, name)
            ] + [row]
            out.mkdir(parents=True, exist_ok=True)
            results_path.write_text(json.dumps(results, indent=1))
            if not args.keep:
                shutil.rmtree(run)
            print_row(row, header=len(rows) == 1)


def print_row(r: dict, header: bool) -> None:
    if header:
        print(
            f"{'case':<9} {'variant':<14} {'obj PSNR':>8} {'PSNR':>6} {'SSIM':>6} {'steps':>6} "
            f"{'train s':>7} {'main s':>7} {'refine s':>8} {'detail s':>8} {'eval s':>6} "
            f"{'total s':>7} {'rays/s':>7} {'smp/ray':>7} {'samples/s':>9} {'peak MB':>7}",
            flush=True,
        )
    print(
        f"{r['case']:<9} {r['variant']:<14} {r.get('heldout_psnr_object', float('nan')):>8.2f} "
        f"{r['heldout_psnr']:>6.2f} {r['heldout_ssim']:>6.3f} {r['iterations']:>6} "
        f"{r['train_seconds']:>7.1f} {r.get('main_seconds', float('nan')):>7.1f} "
        f"{r.get('refine_seconds', float('nan')):>8.1f} {r.get('detail_seconds', 0.0):>8.1f} "
        f"{r.get('eval_seconds', float('nan')):>6.1f} {r.get('total_seconds', float('nan')):>7.1f} "
        f"{r['rays_per_second']:>7.0f} {r['samples_per_ray']:>7} "
        f"{r.get('samples_per_second', 0):>9.0f} {r['peak_rss_mb']:>7.0f}",
        flush=True,
    )


if __name__ == "__main__":
    main()
