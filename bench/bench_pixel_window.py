"""What casting only the proxy's pixel window saves (`Camera.pixel_window`), side by side.

On a fitted run (its template and refined proxy): the fit's ray pool of every training view,
whole-image renders of the held-out views (the fit's metrics: 2 x 2 rays a pixel and the
silhouette pixels again), and the silhouettes of the proxy in every training view (what each
proxy refinement casts), each timed with the window and with every pixel cast (the same
sampler without `pixel_window`). The results are compared too: they must be equal.

    .venv/bin/python bench/bench_pixel_window.py RUN [--threads 2] [--repeats 3]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see sine_cli.py

import argparse
import time

import numpy as np
import torch

from recon.fit import load_fitted
from recon.fit_data import build_ray_pool, load_views
from recon.fit_proxy import make_sampler, template_proxy
from recon.rundir import RunDir
from render.raycast import MeshRaycaster
from render.renderer import render_image


class EveryPixel:
    """A sampler that casts every pixel (no `pixel_window`)."""

    def __init__(self, sampler):
        self.sampler = sampler

    def __getattr__(self, name):
        if name == "pixel_window":
            raise AttributeError(name)
        return getattr(self.sampler, name)


class EveryPixelMesh(MeshRaycaster):
    """`cast_camera` over every pixel, as before the window."""

    def cast_camera(self, cam):
        return self.cast(*cam.rays())


def timed(fn, repeats: int):
    """(best seconds of `repeats`, the last result)."""
    best, out = float("inf"), None
    for _ in range(repeats):
        t = time.perf_counter()
        out = fn()
        best = min(best, time.perf_counter() - t)
    return best, out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a run directory with a fitted template")
    ap.add_argument("--threads", type=int, default=2)
    ap.add_argument("--repeats", type=int, default=3)
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    run = RunDir(args.run)
    field, background, cfg = load_fitted(run.root)
    sampler = make_sampler(cfg, run)
    every = EveryPixel(sampler)
    train, test = load_views(run, "train"), load_views(run, "test")
    device = torch.device("cpu")
    rows = []

    def pool(s):
        return build_ray_pool(train, s, device)

    (t_win, a), (t_all, b) = (
        timed(lambda: pool(sampler), args.repeats),
        timed(lambda: pool(every), args.repeats),
    )
    same = all(torch.equal(getattr(a, k), getattr(b, k)) for k in ("origins", "rgb", "miss_rgb"))
    rows.append(("ray pool", f"{len(train)} training views", t_win, t_all, same))

    def renders(s):
        return [
            render_image(cam, field, s, background, cfg.eval_chunk, device, cfg.supersample)
            for cam, _, _ in test
        ]

    (t_win, a), (t_all, b) = timed(lambda: renders(sampler), 1), timed(lambda: renders(every), 1)
    same = all(np.array_equal(x["rgb"], y["rgb"]) for x, y in zip(a, b, strict=True))
    rows.append(("held-out renders", f"{len(test)} views, supersample {cfg.supersample}",
                 t_win, t_all, same))  # fmt: skip

    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(template_proxy(run)))
    window, plain = MeshRaycaster(mesh), EveryPixelMesh(mesh)
    (t_win, a), (t_all, b) = (
        timed(lambda c=c: [c.silhouette(cam) for cam, _, _ in train], args.repeats)
        for c in (window, plain)
    )
    same = all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    rows.append(("proxy silhouettes", f"{len(train)} training views", t_win, t_all, same))

    print(f"{run.root} ({args.threads} threads; best of {args.repeats}, renders once)")
    print(f"{'what':18s} {'of':28s} {'window s':>9s} {'every pixel s':>14s} {'speed-up':>9s} same")
    for what, of, t_win, t_all, same in rows:
        print(f"{what:18s} {of:28s} {t_win:9.2f} {t_all:14.2f} {t_all / t_win:8.2f}x {same}")


if __name__ == "__main__":
    main()
