"""What the user gives an edit, read and checked: the target image, its silhouette, the region.

- The target's silhouette comes from its alpha channel, else a given mask, else background
  keying (`recon.masks.segment_foreground`), in that order.
- A target of another size than the run's working images is resized (with a one-line note) when
  the aspect ratio matches, refused otherwise. A target whose silhouette is empty is refused.
- The editable region is the user's painted region (`--region`), else where the target and the
  template's rendering of that view differ (silhouette or colour), dilated.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from render.errors import SineError
from render.io import read_image_rgba, read_mask


@dataclass
class Target:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1]
    silhouette: np.ndarray  # [H, W] float32 in {0, 1}
    silhouette_source: str  # alpha | mask | keying


def _fit_size(
    image: np.ndarray, size: tuple[int, int], what: str, path, say: bool = True
) -> np.ndarray:
    """Resizes image [h, w, ...] to size (W, H) when the aspect ratio matches (saying so in one
    line when `say`); else an error."""
    h, w = image.shape[:2]
    width, height = size
    if (w, h) == (width, height):
        return image
    if abs(w / h - width / height) > 0.01:
        raise SineError(
            f"{what} {path} is {w}x{h} but the run's images are {width}x{height} (another aspect "
            f"ratio); make it from `sine snapshot` of the same view"
        )
    if say:
        print(f"note: {what} {path} is {w}x{h}; resized to the run's {width}x{height}")
    interp = cv2.INTER_AREA if w > width else cv2.INTER_LINEAR
    return cv2.resize(image, (width, height), interpolation=interp)


def _require_silhouette(silhouette: np.ndarray, path, source: str) -> None:
    """A SineError when the target's silhouette (from `source`) holds no object pixel."""
    if silhouette.any():
        return
    why = {
        "alpha": "it is fully transparent (alpha 0 everywhere)",
        "mask": "its mask is black everywhere",
        "keying": "no object stands out from the background",
    }[source]
    raise SineError(
        f"the target {path} has an empty silhouette: {why}; give the edited view with the "
        "object in it (erase only what should disappear)"
    )


def read_target(path, size: tuple[int, int], mask_path=None, background=None) -> Target:
    """The target image at the run's working size (W, H) with its silhouette."""
    path = Path(path)
    if not path.is_file():
        raise SineError(f"target image {path} does not exist")
    rgb, alpha = read_image_rgba(path)
    rgb = _fit_size(rgb, size, "target", path)
    if alpha is not None and (alpha < 0.5).any():
        alpha = _fit_size(alpha, size, "target alpha", path, say=False)
        sil = alpha > 0.5
        source = "alpha"
        if background is not None:  # what the user erased shows the run's background
            a = alpha[..., None]
            rgb = rgb * a + np.asarray(background, np.float32) * (1 - a)
    elif mask_path is not None:
        if not Path(mask_path).is_file():
            raise SineError(f"target mask {mask_path} does not exist")
        sil = _fit_size(read_mask(mask_path).astype(np.float32), size, "mask", mask_path) > 0.5
        source = "mask"
    else:
        from recon.masks import segment_foreground

        sil = segment_foreground(rgb)
        source = "keying"
    _require_silhouette(sil, path, source)
    return Target(rgb.astype(np.float32), sil.astype(np.float32), source)


def read_region(path, size: tuple[int, int]) -> np.ndarray:
    """A painted region PNG (white on black) -> [H, W] bool at the run's size."""
    if not Path(path).is_file():
        raise SineError(f"region {path} does not exist")
    region = read_mask(path).astype(np.float32)
    region = _fit_size(region, size, "region", path) > 0.5
    if not region.any():
        raise SineError(f"region {path} is empty: paint the part to edit in white on black")
    return region


def difference_region(
    target: Target,
    template_rgb: np.ndarray,
    template_alpha: np.ndarray,
    dilate_px: int,
    follow_silhouette: bool = False,
) -> np.ndarray:
    """[H, W] bool where target and template differ (silhouette, or colour by > 0.15 after a
    slight blur), dilated; raises "nothing to edit" when they do not differ.

    The blur and an opening (5x5) keep the template's own rendering error (thin details it renders
    soft) out of the region: what remains are areas the edit changed. `follow_silhouette`
    (geometric edits): when the silhouette changed, only colour changes connected to a silhouette
    change count (a shape edit moves its part's outline; isolated colour differences elsewhere are
    the template's rendering error, e.g. a capture used as the target)."""
    opened = np.ones((5, 5), np.uint8)
    sil_diff = (target.silhouette > 0.5) != (template_alpha > 0.5)
    sil_diff = cv2.morphologyEx(sil_diff.astype(np.uint8), cv2.MORPH_OPEN, opened)
    blur = lambda im: cv2.GaussianBlur(im, (0, 0), 1.5)  # noqa: E731
    colour_diff = np.abs(blur(target.rgb) - blur(template_rgb)).max(axis=-1) > 0.15
    changed = ((sil_diff > 0) | colour_diff).astype(np.uint8)
    changed = cv2.morphologyEx(changed, cv2.MORPH_OPEN, opened)
    if changed.sum() < 0.0005 * changed.size:
        raise SineError(
            "nothing to edit: the target matches the template's rendering of this view (changes "
            "narrower than 5 pixels are taken for the template's own rendering error); edit the "
            "snapshot (`sine snapshot`) or make a target with `sine target`, or paint the part "
            "that changed and give it with --region"
        )
    if follow_silhouette and sil_diff.any():
        # components of the change (bridged over a few pixels) that contain a silhouette change
        bridged = cv2.dilate(changed, np.ones((2 * dilate_px + 1,) * 2, np.uint8))
        _, labels = cv2.connectedComponents(bridged)
        keep = np.unique(labels[(sil_diff > 0) & (bridged > 0)])
        changed = changed * np.isin(labels, keep[keep > 0])
    size = 2 * dilate_px + 1
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
    return cv2.dilate(changed.astype(np.uint8), kernel) > 0
