"""Where a texture edit's held-out error is: edges or interiors of what the edit changed, or the
rest of the object. A diagnostic on a finished `bench/bench_edit_texture.py` object folder.

    python bench/bench_edit_texture_errors.py DIR/toycar ours naive_naive_s0 [--threads 1]

For every edit named (RUN/edits/NAME of DIR/OBJECT/run) and for the template itself, on the
bench's held-out views (every 4th view, the edited view excluded), the squared error (RGB,
summed over pixels and views) against the ground-truth edit (the template: against the
*unedited* ground truth, its own error, what an edit cannot beat), split into:
- changed, edge: pixels the GT edit changed that lie within 1 px of a GT edge (Sobel gradient of
  the grey image > 0.25): stripes, checker squares, silhouettes;
- changed, interior: the other changed pixels;
- unchanged: object pixels (GT mask or rendered opacity > 0.5) the GT edit did not change.
Prints a table and writes DIR/OBJECT/errors.json.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import cv2
import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

EDGE_GRADIENT = 0.25  # Sobel magnitude of the GT's grey image (values in [0, 1])


def edge_pixels(image: np.ndarray) -> np.ndarray:
    """[H, W] bool: within 1 px of a strong gradient of `image` [H, W, 3]."""
    grey = cv2.cvtColor((image * 255).astype(np.uint8), cv2.COLOR_RGB2GRAY).astype(np.float32)
    grey /= 255.0
    magnitude = np.hypot(cv2.Sobel(grey, cv2.CV_32F, 1, 0), cv2.Sobel(grey, cv2.CV_32F, 0, 1))
    strong = (magnitude > EDGE_GRADIENT).astype(np.uint8)
    return cv2.dilate(strong, np.ones((3, 3), np.uint8)) > 0


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("object_dir", type=Path, help="DIR/OBJECT of bench_edit_texture.py")
    ap.add_argument("edits", nargs="+", help="edit names in its run (e.g. ours naive)")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    args = ap.parse_args()

    from bench_edit_texture import changed_pixels, heldout_views, open_object

    from edit.scene import load_scene
    from render.io import read_image, read_mask, write_json

    run, syn, frames, k = open_object(args.object_dir, args.threads)
    views = heldout_views(len(frames), k)
    scenes = {"template": load_scene(run.root)}
    scenes.update({name: load_scene(run.root, edit=name) for name in args.edits})
    parts = ("changed_edge", "changed_interior", "unchanged")
    errors = {name: dict.fromkeys(parts, 0.0) for name in scenes}
    counts = dict.fromkeys(parts, 0)
    for v in views:
        cam = frames[v]
        edited = read_image(syn / "edits" / "texture" / "images" / cam.name)
        original = read_image(syn / "images" / cam.name)
        gt_mask = read_mask(syn / "edits" / "texture" / "masks" / cam.name)
        changed = changed_pixels(syn, cam.name)
        edge = edge_pixels(edited)
        for name, scene in scenes.items():
            out = scene.render_view(cam)
            squared = ((np.clip(out["rgb"], 0, 1) - (original if name == "template" else edited))
                       ** 2).sum(axis=-1)  # fmt: skip
            obj = gt_mask | (out["opacity"] > 0.5)
            masks = {
                "changed_edge": changed & edge,
                "changed_interior": changed & ~edge,
                "unchanged": obj & ~changed,
            }
            for part, mask in masks.items():
                errors[name][part] += float(squared[mask].sum())
                if name == "template":
                    counts[part] += int(mask.sum())
    print(f"{'':16s}" + "".join(f"{p:>18s}" for p in parts))
    print(f"{'pixels':16s}" + "".join(f"{counts[p]:18d}" for p in parts))
    for name, e in errors.items():
        print(f"{name:16s}" + "".join(f"{e[p]:18.1f}" for p in parts))
    write_json(
        args.object_dir / "errors.json",
        {"views": views, "pixels": counts, "squared_error": errors},
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
