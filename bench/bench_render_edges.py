"""Rays per pixel when rendering a template: the cost and the held-out quality, side by side.

For each fitted run (a `sine fit` output, e.g. `bench/bench_fit.py --keep`'s CASE/run_NAME),
renders the held-out views with the same field and sampler under each variant:

  1            one ray through each pixel centre
  2            2 x 2 rays per pixel, box-filtered (silhouette pixels not rendered again)
  2+edges      2 x 2, and the pixels a silhouette crosses (their 2 x 2 rays' opacities differ
               by more than render.renderer.EDGE_SPREAD) again with 4 x 4 (the default)
  3, 4         3 x 3 / 4 x 4 rays for every pixel

and prints held-out PSNR on object pixels (the views' masks) and over whole images, seconds per
view, field samples per pixel and the share of pixels rendered again. One process, one variant
after the other on the same machine; `--threads` torch threads.

    .venv/bin/python bench/bench_render_edges.py RUN [RUN ...] [--threads 2] [--json OUT.json]
        [--picture OUT.png]

`--picture`: the first run's first held-out view, its 64 x 64 pixels around the most
re-rendered spot enlarged 4x: 2 x 2 | 2 x 2 + edges | truth; below, |error| of each (x8).
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see sine_cli.py

import argparse
import json
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from recon.fit import load_fitted  # noqa: E402
from recon.fit_data import load_views  # noqa: E402
from recon.fit_proxy import make_sampler  # noqa: E402
from recon.rundir import RunDir  # noqa: E402
from render.io import write_image  # noqa: E402
from render.metrics import masked_psnr, psnr  # noqa: E402
from render.renderer import render_image  # noqa: E402

VARIANTS = {  # name: (supersample, edge_supersample)
    "1": (1, 1),
    "2": (2, 2),
    "2+edges": (2, None),
    "3": (3, 3),
    "4": (4, 4),
}


def fitted(run_path: Path):
    """(field, background, sampler, held-out views [(camera, image, mask)]) of a fitted run."""
    run = RunDir(run_path)
    field, background, cfg = load_fitted(run.root)
    return field, background, make_sampler(cfg, run), list(load_views(run, "test"))


def measure(run_path: Path) -> list[dict]:
    """One row per variant for the held-out views of a fitted run."""
    field, background, sampler, views = fitted(run_path)
    device = torch.device("cpu")
    rows = []
    for name, (s, t) in VARIANTS.items():
        obj, whole, samples, again = [], [], [], []
        start = time.perf_counter()
        for cam, image, mask in views:
            out = render_image(cam, field, sampler, background, 16384, device, s, (), t)
            pred = np.clip(out["rgb"], 0.0, 1.0)
            whole.append(psnr(pred, image))
            if mask is not None and mask.any():
                obj.append(masked_psnr(pred, image, mask))
            samples.append(float(out["samples_per_pixel"]))
            again.append(float(np.mean(out["rendered_again"])))
        seconds = (time.perf_counter() - start) / max(len(views), 1)
        rows.append(
            {
                "run": str(run_path),
                "variant": name,
                "psnr_object": float(np.mean(obj)) if obj else float("nan"),
                "psnr": float(np.mean(whole)),
                "seconds_per_view": seconds,
                "samples_per_pixel": float(np.mean(samples)),
                "pixels_again": float(np.mean(again)),
                "views": len(views),
            }
        )
    return rows


def picture(run_path: Path, path: Path) -> None:
    """See the module doc (`--picture`)."""
    field, background, sampler, views = fitted(run_path)
    cam, image, _ = views[0]
    device = torch.device("cpu")
    plain, edges = (
        render_image(cam, field, sampler, background, 16384, device, 2, (), t) for t in (2, None)
    )
    again = edges["rendered_again"].astype(np.float32)
    density = cv2.blur(again, (31, 31))  # where most pixels were rendered again
    y, x = np.unravel_index(np.argmax(density), density.shape)
    y0 = int(np.clip(y - 32, 0, image.shape[0] - 64))
    x0 = int(np.clip(x - 32, 0, image.shape[1] - 64))

    def crop(a):
        a = np.clip(a[y0 : y0 + 64, x0 : x0 + 64], 0.0, 1.0)
        return np.kron(a, np.ones((4, 4, 1), np.float32))

    top = [crop(plain["rgb"]), crop(edges["rgb"]), crop(image)]
    bottom = [crop(8 * np.abs(plain["rgb"] - image)), crop(8 * np.abs(edges["rgb"] - image))]
    bottom.append(np.ones_like(top[0]))
    write_image(path, np.concatenate([np.concatenate(top, 1), np.concatenate(bottom, 1)], 0))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="fitted run directories")
    parser.add_argument("--threads", type=int, default=2, help="torch threads")
    parser.add_argument("--json", type=Path, default=None, help="also write the rows here")
    parser.add_argument("--picture", type=Path, default=None, help="write the crops (see above)")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    rows = []
    print(
        f"{'run':<34} {'variant':<8} {'obj PSNR':>8} {'PSNR':>6} {'s/view':>7} "
        f"{'samples/px':>10} {'again':>6}"
    )
    for run in args.runs:
        for r in measure(run):
            rows.append(r)
            name = "/".join(Path(r["run"]).parts[-2:])[-34:]
            print(
                f"{name:<34} {r['variant']:<8} {r['psnr_object']:>8.2f} {r['psnr']:>6.2f} "
                f"{r['seconds_per_view']:>7.2f} {r['samples_per_pixel']:>10.1f} "
                f"{r['pixels_again'] * 100:>5.1f}%",
                flush=True,
            )
    if args.json is not None:
        args.json.write_text(json.dumps({"rows": rows}, indent=2))
    if args.picture is not None:
        picture(args.runs[0], args.picture)


if __name__ == "__main__":
    main()
