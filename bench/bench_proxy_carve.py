"""The recon proxy with and without carving (`sine recon --proxy-carve`), on existing run dirs.

For each RUN (made by `sine recon`) the proxy is rebuilt from the run's own depth maps, masks
and visual hull exactly as the proxy_mesh stage does, once per variant, and scored against:
- the run's depth maps, ray by ray (|proxy hit - depth| along the ray on pixels with depth):
  with dataset depth (synthetic captures) that depth is the truth; with stereo depth it is a
  consistency figure only. The fit samples a band of +-0.04 around the proxy, so the fraction
  of pixels off by more than 0.04 is surface the field cannot reach;
- the masks: mean silhouette IoU of the proxy's ray-cast silhouette (recon.report's figure).

    .venv/bin/python bench/bench_proxy_carve.py bench/out/fit_aa/toycar/run bench/out/fit/dinosaur/run
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from recon.pipeline import Pipeline  # noqa: E402
from recon.proxy_mesh import build_proxy, closing_depths, depth_disagreement  # noqa: E402
from recon.proxy_refine import silhouette_ious  # noqa: E402
from recon.recon_config import ReconConfig, proxy_params  # noqa: E402
from recon.rundir import RunDir  # noqa: E402
from render.io import read_depth  # noqa: E402


def main() -> None:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("runs", nargs="+", type=Path, help="run directories made by `sine recon`")
    args = ap.parse_args()
    print(
        f"{'run':<28} {'variant':<10} {'median':>7} {'>0.02':>6} {'>0.04':>6} "
        f"{'sil IoU':>7} {'tris':>6} {'s':>5}"
    )
    for path in args.runs:
        run = RunDir(path)
        cams = run.load_cameras().frames
        depths = [read_depth(run.depth_path(c.name)) for c in cams]
        pipe = Pipeline(run, ReconConfig())
        masks = pipe.masks_for(cams)
        hull = pipe._hull(cams, masks)
        closing = closing_depths(hull.vertices, hull.faces, hull.open_faces)
        params = proxy_params(ReconConfig())
        label = f"{path.parent.name}/{path.name}"
        for variant, carve in (("no carve", False), ("carve", True)):
            t0 = time.perf_counter()
            mesh = build_proxy(cams, depths, masks, params, closing, carve=carve, progress=False)
            seconds = time.perf_counter() - t0
            err = depth_disagreement(mesh, cams, depths)
            iou = float(np.mean(silhouette_ious(mesh, cams, masks)))
            print(
                f"{label:<28} {variant:<10} {np.median(err):>7.4f} {np.mean(err > 0.02):>6.3f} "
                f"{np.mean(err > 0.04):>6.3f} {iou:>7.3f} {len(mesh.triangles):>6} "
                f"{seconds:>5.1f}",
                flush=True,
            )


if __name__ == "__main__":
    main()
