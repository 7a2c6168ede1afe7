"""How well could a template render the held-out views? Each held-out view is predicted by its two
ring neighbours' photos, warped into it through the template's own depth and averaged (simple
image-based rendering), and scored inside its mask beside the template's render, on the pixels
both neighbours see (the template's depth decides what they see).

If the warped neighbours score far above the template, the capture's views agree with each other
and the template is what loses the detail (underfit); if they score like the template, the views
themselves disagree (lighting that turns with the camera, pose error) and no field does much
better. bench/HISTORY.md "The colour-detail phase" has the oxford-dinosaur's table.

    .venv/bin/python bench/bench_view_consistency.py RUN [RUN ...] [--threads 2]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see sine_cli.py

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from edit.scene import load_scene  # noqa: E402
from recon.rundir import RunDir  # noqa: E402
from render.io import read_image, read_mask  # noqa: E402
from render.metrics import psnr  # noqa: E402

DEPTH_TOLERANCE = 0.01  # run units: a warped pixel is seen when the neighbour's depth agrees


def warp_into(camera, points: np.ndarray, neighbour, image: np.ndarray, depth: np.ndarray):
    """The neighbour's `image` [H', W', 3] sampled where `points` [H*W, 3] (camera's pixels
    lifted to the surface) project, and whether the neighbour sees them ([H, W, 3], [H, W])."""
    pixels, z = neighbour.project(points)
    shape = (camera.height, camera.width)
    map_x = (pixels[:, 0] - 0.5).reshape(shape).astype(np.float32)  # pixel centres at +0.5
    map_y = (pixels[:, 1] - 0.5).reshape(shape).astype(np.float32)
    warped = cv2.remap(image, map_x, map_y, cv2.INTER_LANCZOS4, borderMode=cv2.BORDER_REPLICATE)
    seen_depth = cv2.remap(depth, map_x, map_y, cv2.INTER_LINEAR)
    return warped, np.abs(seen_depth - z.reshape(shape)) < DEPTH_TOLERANCE


def score_run(root: Path) -> None:
    """Prints one table row per held-out view of the run at `root`."""
    run = RunDir(root)
    scene = load_scene(run.root)
    frames = run.load_cameras().frames
    renders = {}

    def render(i):
        if i not in renders:
            with torch.no_grad():
                renders[i] = scene.render_view(frames[i])
        return renders[i]

    for i, cam in enumerate(frames):
        if cam.split != "test":
            continue
        photo = read_image(run.image_path(cam.name))
        mask = read_mask(run.mask_path(cam.name))
        mine = render(i)
        pixels = cam.pixel_grid()
        origins, dirs = cam.rays(pixels)
        distance = mine["z"].reshape(-1) / cam.z_per_unit_distance(pixels)
        points = origins + dirs * distance[:, None]
        total = np.zeros_like(photo)
        seen = np.zeros(mask.shape, np.int32)
        for step in (-1, 1):  # the ring neighbours
            j = (i + step) % len(frames)
            image = read_image(run.image_path(frames[j].name))
            warped, visible = warp_into(cam, points, frames[j], image, render(j)["z"])
            total += warped * visible[..., None]
            seen += visible
        both = mask & (seen == 2)
        template = np.clip(mine["rgb"], 0, 1)
        neighbours = total / 2
        print(
            f"| {run.root.name} | {cam.name} | {both.sum() / max(mask.sum(), 1):.2f} | "
            f"{psnr(template[both], photo[both]):.2f} | {psnr(neighbours[both], photo[both]):.2f} |",
            flush=True,
        )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories with a template")
    parser.add_argument("--threads", type=int, default=2, help="torch CPU threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    print("| run | view | pixels both neighbours see | template | two warped neighbours |")
    print("|---|---|---:|---:|---:|")
    for root in args.runs:
        score_run(root)


if __name__ == "__main__":
    main()
