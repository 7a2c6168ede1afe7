"""How far one colour map carries a texture edit: the ceiling of a compositor that recolours
the edited part with ONE colour map of the template's colours (the compositor's shared
transform: linear, A c + b, or with the quadratic term). A diagnostic on a finished
`bench/bench_edit_texture.py` object folder (its template only; no edit needed).

    python bench/bench_edit_texture.py --out DIR --objects toycar --methods template
    python bench/bench_colour_map.py DIR/toycar [--threads 1]

The map is fitted on the edit view K (the bench's: the training view where the GT edit changes
the most pixels) from the template's rendering to the GT edited image, over the edited part's GT
label pixels, by `edit.compositor.fit_shared_transform` (least squares with a ridge r towards no
change, relative to the colours' second moments) for several ridges. It is then applied to the
template's rendering of the held-out views (every 4th view, K excluded) on the part's GT label
pixels and scored against the GT edit there (PSNR over those pixels); "identity" is the template
unchanged, "oracle" the map fitted on the held-out pixels themselves. The GT region is what an
edit does not have: this measures the map, not where the edit applies it.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parent))

RIDGES = (0.0, 1e-4, 1e-3, 1e-2, 1e-1)


def fitted_map(source: np.ndarray, target: np.ndarray, ridge: float, quadratic: bool):
    """The compositor's shared transform (`edit.compositor.fit_shared_transform`, the part's own
    colours with g = 1) fitted from `source` [N, 3] to `target` [N, 3] -> colours [M, 3] -> the
    mapped colours [M, 3] (the compositor applied with I_m = 0)."""
    import torch

    from edit.compositor import Compositor, fit_shared_transform

    comp = Compositor(head="affine", quadratic=quadratic)
    src, tgt = torch.from_numpy(source).float(), torch.from_numpy(target).float()
    fit_shared_transform(comp, src, tgt, torch.ones(len(src)), src, ridge=ridge)

    def apply(colours: np.ndarray) -> np.ndarray:
        image = torch.from_numpy(colours).float().T[None, :, None]  # [1, 3, 1, M]
        with torch.no_grad():
            out = comp(image, torch.zeros_like(image), torch.ones_like(image[:, :1]), image)
        return out[0, :, 0].T.numpy()

    return apply


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("object_dir", type=Path, help="DIR/OBJECT of bench_edit_texture.py")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    args = ap.parse_args()

    from bench_edit_texture import heldout_views, open_object, part_label, psnr

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
    rows = {"identity": psnr(source, target)}
    for kind, quadratic in (("linear", False), ("quadratic", True)):
        for ridge in RIDGES:
            mapped = fitted_map(source_k, target_k, ridge, quadratic)(source)
            rows[f"{kind} ridge {ridge:g}"] = psnr(mapped, target)
        rows[f"{kind} oracle"] = psnr(fitted_map(source, target, 0.0, quadratic)(source), target)
    print(f"view K {k}: {len(source_k)} part pixels, colour covariance eigenvalues "
          + " ".join(f"{e:.2g}" for e in spread))  # fmt: skip
    print(f"{'map':24s}{'held-out part PSNR':>20s}")
    for name, value in rows.items():
        print(f"{name:24s}{value:20.2f}")
    write_json(
        args.object_dir / "colour_map.json",
        {"view": k, "part_pixels_k": len(source_k), "heldout_part_psnr": rows},
    )
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
