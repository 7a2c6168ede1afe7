"""How far one colour map carries a texture edit: the ceiling of a compositor that recolours
the edited part with ONE affine map of the template's colours. A diagnostic on a finished
`bench/bench_edit_texture.py` object folder (its template only; no edit needed).

    python bench/bench_edit_texture.py --out DIR --objects toycar --methods template
    python bench/bench_colour_map.py DIR/toycar [--threads 1]

The map target - source ~ A source + b is fitted on the edit view K (the bench's: the training
view where the GT edit changes the most pixels) from the template's rendering to the GT edited
image, over the edited part's GT label pixels, by least squares with a ridge r on A
(A = C_dx (C_xx + r I)^-1 over centred colours; b free). It is then applied to the template's
rendering of the held-out views (every 4th view, K excluded) on the part's GT label pixels and
scored against the GT edit there (PSNR over those pixels), for several ridges; "identity" is the
template unchanged, "oracle" the map fitted on the held-out pixels themselves. The GT region is
what an edit does not have: this measures the map, not where the edit applies it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

RIDGES = (0.0, 1e-4, 1e-3, 1e-2, 1e-1)


def fit_colour_map(source: np.ndarray, target: np.ndarray, ridge: float) -> np.ndarray:
    """[A.flatten(), b] [12] of target - source ~ A source + b (source, target [N, 3]), with a
    ridge on A: directions the source colours barely vary along leave A's action near zero."""
    x, d = source.astype(np.float64), (target - source).astype(np.float64)
    xc, dc = x - x.mean(0), d - d.mean(0)
    cov_xx, cov_dx = xc.T @ xc / len(x), dc.T @ xc / len(x)
    a = np.linalg.solve(cov_xx + ridge * np.eye(3), cov_dx.T).T
    return np.concatenate([a.ravel(), d.mean(0) - a @ x.mean(0)])


def mapped_psnr(colour_map: np.ndarray, source: np.ndarray, target: np.ndarray) -> float:
    """PSNR of the colours `source` [N, 3] through the map against `target` [N, 3]."""
    from bench_edit_texture import psnr

    a, b = colour_map[:9].reshape(3, 3), colour_map[9:]
    return psnr(np.clip(source + source @ a.T + b, 0.0, 1.0), target)


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("object_dir", type=Path, help="DIR/OBJECT of bench_edit_texture.py")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    args = ap.parse_args()

    from bench_edit_texture import heldout_views, open_object, part_label

    from edit.scene import load_scene
    from render.io import read_image, write_json

    run, syn, frames, k = open_object(args.object_dir, args.threads)
    scene = load_scene(run.root)

    def part_colours(cam) -> tuple[np.ndarray, np.ndarray]:
        """The template's and the GT edit's colours [N, 3] of the part's pixels in a view."""
        out = scene.render_view(cam)
        pixels = part_label(syn, cam.name) & (out["opacity"] > 0.5)
        edited = read_image(syn / "edits" / "texture" / "images" / cam.name)
        return np.clip(out["rgb"], 0, 1)[pixels], edited[pixels]

    source_k, target_k = part_colours(frames[k])
    held = [part_colours(frames[v]) for v in heldout_views(len(frames), k)]
    source, target = np.concatenate([h[0] for h in held]), np.concatenate([h[1] for h in held])
    spread = np.linalg.eigvalsh(np.cov(source_k.T))
    rows = {"identity": mapped_psnr(np.zeros(12), source, target)}
    for ridge in RIDGES:
        rows[f"ridge {ridge:g}"] = mapped_psnr(
            fit_colour_map(source_k, target_k, ridge), source, target
        )
    rows["oracle"] = mapped_psnr(fit_colour_map(source, target, 0.0), source, target)
    print(f"view K {k}: {len(source_k)} part pixels, colour covariance eigenvalues "
          + " ".join(f"{e:.2g}" for e in spread))  # fmt: skip
    print(f"{'map':16s}{'held-out part PSNR':>20s}")
    for name, value in rows.items():
        print(f"{name:16s}{value:20.2f}")
    write_json(
        args.object_dir / "colour_map.json",
        {"view": k, "part_pixels_k": len(source_k), "heldout_part_psnr": rows},
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
