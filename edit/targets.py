"""Editing targets without a 2D editor (`sine target`): pure 2D operations on one view.

Every function takes a view's image [H, W, 3] (float RGB in [0, 1], composited over its
background, as `sine snapshot` writes it) and, for the geometric ones, its alpha [H, W] in [0, 1]
(rendered opacity or capture mask), and returns new arrays; inputs are never modified.

Pixel coordinates are those an image editor shows: x = column, y = row, 0-based, the centre of
pixel (row i, column j) at (x, y) = (j, i); fractions are allowed.

Geometric operations move the object's premultiplied colour and its alpha, then composite the
result over the backdrop: the background colour (a render's flat background), or a backdrop image
(a capture's own pixels where the object is not, inpainted where it is: `inpaint_backdrop`).
Where the moved object no longer covers a pixel, the backdrop shows (alpha 0).
"""

from __future__ import annotations

import cv2
import numpy as np

from render.errors import SineError

Point = tuple[float, float]


# ---- compositing helpers ------------------------------------------------------------------
def background_color(image: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """Median colour [3] of the pixels the object does not cover (alpha < 0.01); white if none."""
    free = alpha < 0.01
    if not free.any():
        return np.ones(3, np.float32)
    return np.median(image[free], axis=0).astype(np.float32)


def inpaint_backdrop(image: np.ndarray, alpha: np.ndarray, radius: int = 5) -> np.ndarray:
    """Backdrop [H, W, 3]: the image where alpha is 0, inpainted (OpenCV Telea) under the object.
    For captures, whose background is not a flat colour."""
    hole = (alpha > 0).astype(np.uint8)
    if not hole.any():
        return image.astype(np.float32, copy=True)
    hole = cv2.dilate(hole, np.ones((3, 3), np.uint8))
    image8 = (np.clip(image, 0, 1) * 255 + 0.5).astype(np.uint8)
    filled = cv2.inpaint(image8, hole, radius, cv2.INPAINT_TELEA).astype(np.float32) / 255
    return np.where(alpha[..., None] > 0, filled, image).astype(np.float32)


def _backdrop(image: np.ndarray, alpha: np.ndarray, background) -> np.ndarray:
    """Backdrop [H, W, 3] from a colour [3], an image [H, W, 3] or None (median background)."""
    if background is None:
        background = background_color(image, alpha)
    background = np.asarray(background, np.float32)
    if background.shape == image.shape:
        return background
    return np.broadcast_to(background.reshape(1, 1, 3), image.shape).astype(np.float32)


def _premultiplied(image: np.ndarray, alpha: np.ndarray, backdrop: np.ndarray) -> np.ndarray:
    """The object's own colour times its alpha [H, W, 3]: image = premult + (1 - alpha) backdrop."""
    a = alpha[..., None]
    return np.clip(image - (1.0 - a) * backdrop, 0.0, a).astype(np.float32)


def _check_inputs(image: np.ndarray, alpha: np.ndarray, mask=None) -> None:
    if image.ndim != 3 or image.shape[2] != 3:
        raise SineError(f"expected an RGB image [H, W, 3], got shape {image.shape}")
    if alpha.shape != image.shape[:2]:
        raise SineError(f"alpha {alpha.shape} does not match the image {image.shape[:2]}")
    if mask is not None and np.shape(mask) != image.shape[:2]:
        h, w = image.shape[:2]
        mh, mw = np.shape(mask)[:2]
        raise SineError(f"the region is {mw}x{mh} but the image is {w}x{h}")


def _to_float(image, alpha):
    return np.asarray(image, np.float32), np.asarray(alpha, np.float32)


# ---- geometric operations -----------------------------------------------------------------
def border_points(width: int, height: int) -> list[Point]:
    """The image's four corners and four edge midpoints (pinned by default in `warp_target`)."""
    xs, ys = (0.0, (width - 1) / 2, width - 1.0), (0.0, (height - 1) / 2, height - 1.0)
    return [(x, y) for y in ys for x in xs if not (x == xs[1] and y == ys[1])]


def tps_inverse_map(
    handles: list[tuple[Point, Point]], anchors: list[Point], width: int, height: int
) -> tuple[np.ndarray, np.ndarray]:
    """Thin-plate spline that maps each output pixel to where it is read from in the input:
    (map_x, map_y) [H, W] float32 for `cv2.remap`, with map(x1, y1) = (x0, y0) for each handle
    ((x0, y0), (x1, y1)) and map(a) = a for each anchor."""
    from scipy.interpolate import RBFInterpolator

    dst = np.array([h[1] for h in handles] + list(anchors), np.float64).reshape(-1, 2)
    src = np.array([h[0] for h in handles] + list(anchors), np.float64).reshape(-1, 2)
    keys = {tuple(np.round(p, 3)) for p in dst}
    if len(keys) < len(dst):
        raise SineError(
            "two warp control points (handle targets or anchors) are at the same place: "
            "give every handle its own target, away from the anchors and image corners"
        )
    try:
        tps = RBFInterpolator(dst, src - dst, kernel="thin_plate_spline", degree=1)
    except np.linalg.LinAlgError:
        raise SineError("the warp handles are degenerate (e.g. all on one line)") from None
    xs, ys = np.meshgrid(np.arange(width, dtype=np.float32), np.arange(height, dtype=np.float32))
    grid = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64)  # [H * W, 2]
    offset = tps(grid).reshape(height, width, 2).astype(np.float32)
    return xs + offset[..., 0], ys + offset[..., 1]


def warp_target(
    image: np.ndarray,
    alpha: np.ndarray,
    handles: list[tuple[Point, Point]],
    anchors: list[Point] | None = None,
    pin_border: bool = True,
    background=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Drags each handle point (x0, y0) to (x1, y1) with a thin-plate-spline warp of the
    object's pixels and alpha -> (image [H, W, 3], alpha [H, W]).

    The border's corners and edge midpoints (`pin_border`) and the `anchors` stay put; the rest
    of the image bends smoothly in between, so add anchors near the handles to keep nearby parts
    of the object still. `background`: colour [3] or backdrop image [H, W, 3] (default: the median
    colour where alpha is 0)."""
    image, alpha = _to_float(image, alpha)
    _check_inputs(image, alpha)
    h, w = alpha.shape
    if not handles:
        raise SineError("--warp needs at least one handle 'x0,y0>x1,y1'")
    points = [p for pair in handles for p in pair] + list(anchors or [])
    for x, y in points:
        if not (0 <= x <= w - 1 and 0 <= y <= h - 1):
            raise SineError(
                f"warp point ({x:g}, {y:g}) is outside the {w}x{h} image "
                f"(x in 0..{w - 1}, y in 0..{h - 1})"
            )
    pinned = list(anchors or []) + (border_points(w, h) if pin_border else [])
    map_x, map_y = tps_inverse_map(handles, pinned, w, h)
    backdrop = _backdrop(image, alpha, background)
    premult = _premultiplied(image, alpha, backdrop)
    remap = dict(interpolation=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    new_premult = cv2.remap(premult, map_x, map_y, **remap)
    new_alpha = np.clip(cv2.remap(alpha, map_x, map_y, **remap), 0.0, 1.0)
    out = new_premult + (1.0 - new_alpha[..., None]) * backdrop
    return np.clip(out, 0.0, 1.0).astype(np.float32), new_alpha.astype(np.float32)


def _centroid(weight: np.ndarray) -> Point:
    total = float(weight.sum())
    if total <= 0:
        raise SineError("the region does not cover any pixel of the object (alpha is 0 there)")
    ys, xs = np.indices(weight.shape)
    return float((xs * weight).sum() / total), float((ys * weight).sum() / total)


def _affine_part(
    image: np.ndarray,
    alpha: np.ndarray,
    part: np.ndarray,
    matrix: np.ndarray,
    background,
) -> tuple[np.ndarray, np.ndarray]:
    """Moves the part (weight [H, W] in [0, 1]) of the object by the affine `matrix` [2, 3]
    (output = matrix @ input) over the rest of the object, which stays where it is."""
    h, w = alpha.shape
    backdrop = _backdrop(image, alpha, background)
    premult = _premultiplied(image, alpha, backdrop)
    warp = dict(flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    part_premult = cv2.warpAffine(premult * part[..., None], matrix, (w, h), **warp)
    part_alpha = np.clip(cv2.warpAffine(alpha * part, matrix, (w, h), **warp), 0.0, 1.0)
    rest_premult, rest_alpha = premult * (1.0 - part[..., None]), alpha * (1.0 - part)
    new_alpha = part_alpha + (1.0 - part_alpha) * rest_alpha
    under = rest_premult + (1.0 - rest_alpha[..., None]) * backdrop
    out = part_premult + (1.0 - part_alpha[..., None]) * under
    untouched = (part_alpha == 0) & (part == 0)  # exactly the input there
    out = np.where(untouched[..., None], image, np.clip(out, 0.0, 1.0))
    new_alpha = np.where(untouched, alpha, new_alpha)
    return out.astype(np.float32), new_alpha.astype(np.float32)


def _region_weight(region_mask) -> np.ndarray:
    """bool or [0, 1] weights [H, W] -> float32 weights."""
    return np.clip(np.asarray(region_mask, np.float32), 0.0, 1.0)


def scale_region(
    image: np.ndarray,
    alpha: np.ndarray,
    region_mask: np.ndarray,
    scale: float,
    center: Point | None = None,
    background=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Scales the painted part of the object (region_mask [H, W], bool or weights) by `scale`
    about its centre (alpha-weighted centroid of the painted object pixels, or `center`)
    -> (image, alpha). What the part uncovers becomes backdrop; the rest of the object stays
    where it is, bit-identical where the scaled part does not cover it."""
    image, alpha = _to_float(image, alpha)
    _check_inputs(image, alpha, region_mask)
    if not scale > 0:
        raise SineError(f"--scale must be positive, got {scale}")
    part = _region_weight(region_mask)
    cx, cy = center if center is not None else _centroid(alpha * part)
    matrix = np.array([[scale, 0.0, cx * (1 - scale)], [0.0, scale, cy * (1 - scale)]])
    return _affine_part(image, alpha, part, matrix, background)


def stretch_axis(
    image: np.ndarray,
    alpha: np.ndarray,
    axis: str,
    factor: float,
    about: float | None = None,
    region_mask: np.ndarray | None = None,
    background=None,
) -> tuple[np.ndarray, np.ndarray]:
    """Stretches the object by `factor` along one image axis ("x": widths, "y": heights)
    -> (image, alpha). The line x = about (or y = about) stays put; default: the object's
    alpha-weighted centre. With `region_mask`, only the painted part is stretched (like
    `scale_region` with one axis), the rest stays."""
    image, alpha = _to_float(image, alpha)
    _check_inputs(image, alpha, region_mask)
    if axis not in ("x", "y"):
        raise SineError(f"--stretch-axis must be x or y, got {axis!r}")
    if not factor > 0:
        raise SineError(f"--factor must be positive, got {factor}")
    part = np.ones_like(alpha) if region_mask is None else _region_weight(region_mask)
    if about is None:
        cx, cy = _centroid(alpha * part)
        about = cx if axis == "x" else cy
    sx, sy = (factor, 1.0) if axis == "x" else (1.0, factor)
    ax, ay = (about, 0.0) if axis == "x" else (0.0, about)
    matrix = np.array([[sx, 0.0, ax * (1 - sx)], [0.0, sy, ay * (1 - sy)]])
    return _affine_part(image, alpha, part, matrix, background)


# ---- texture operations -------------------------------------------------------------------
def recolor_region(
    image: np.ndarray, region_mask: np.ndarray, hue_deg: float, saturation: float | None = None
) -> np.ndarray:
    """Rotates the hue (HSV) by `hue_deg` degrees inside the region (bool [H, W]); `saturation`
    multiplies the saturation there (clipped to 1). Value (brightness, hence shading) is kept;
    grey pixels have no hue and stay grey. Pixels outside the region are bit-identical."""
    image = np.asarray(image, np.float32)
    region = np.asarray(region_mask) > 0.5
    _check_inputs(image, np.zeros(image.shape[:2], np.float32), region)
    hsv = cv2.cvtColor(np.clip(image, 0.0, 1.0), cv2.COLOR_RGB2HSV)  # H in [0, 360)
    hsv[..., 0] = np.mod(hsv[..., 0] + hue_deg, 360.0)
    if saturation is not None:
        if saturation < 0:
            raise SineError(f"--saturation must be >= 0, got {saturation}")
        hsv[..., 1] = np.clip(hsv[..., 1] * saturation, 0.0, 1.0)
    recolored = cv2.cvtColor(hsv, cv2.COLOR_HSV2RGB)
    return np.where(region[..., None], recolored, image).astype(np.float32)


def luminance(image: np.ndarray) -> np.ndarray:
    """Rec. 601 luma [H, W] of RGB [H, W, 3]."""
    return image @ np.array([0.299, 0.587, 0.114], np.float32)


def paint_region(
    image: np.ndarray, region_mask: np.ndarray, color, shading: bool = True
) -> np.ndarray:
    """Paints the region (bool [H, W]) with `color` (RGB in [0, 1]) -> image [H, W, 3].

    With `shading`, each pixel gets color * (its luminance / the region's mean luminance),
    clipped to [0, 1]: the part's mean colour is `color` and its light and shade are kept (a
    flat region becomes exactly `color`). Without, the region is one flat colour. Pixels outside
    the region are bit-identical."""
    image = np.asarray(image, np.float32)
    region = np.asarray(region_mask) > 0.5
    _check_inputs(image, np.zeros(image.shape[:2], np.float32), region)
    color = np.asarray(color, np.float32).reshape(1, 1, 3)
    if np.any(color < 0) or np.any(color > 1):
        raise SineError("the paint colour must be RGB in [0, 1] (0..255 on the command line)")
    out = image.copy()
    if not region.any():
        return out
    if shading:
        lum = luminance(image)
        gain = lum / max(float(lum[region].mean()), 1e-6)
        painted = np.clip(color * gain[..., None], 0.0, 1.0)
    else:
        painted = np.broadcast_to(color, image.shape)
    out[region] = painted[region]
    return out


# ---- output -------------------------------------------------------------------------------
def before_after(before: np.ndarray, after: np.ndarray, separator: int = 4) -> np.ndarray:
    """Side by side [H, W1 + separator + W2, 3]: before left, after right, a dark grey bar
    between (the shorter one padded with white at the bottom)."""
    before, after = (np.asarray(a, np.float32)[..., :3] for a in (before, after))
    h = max(before.shape[0], after.shape[0])

    def pad(a):
        return np.pad(a, ((0, h - a.shape[0]), (0, 0), (0, 0)), constant_values=1.0)

    bar = np.full((h, separator, 3), 0.25, np.float32)
    return np.concatenate([pad(before), bar, pad(after)], axis=1)


def write_rgba(path, image: np.ndarray, alpha: np.ndarray, background=None) -> None:
    """Writes an 8-bit RGBA PNG, atomically, of `image` [H, W, 3] composited over `background`
    (colour [3] or backdrop [H, W, 3]) with alpha [H, W] in [0, 1]. The PNG holds straight
    (unassociated) colour, as PNG defines it: composited over the background again it gives
    `image` back (where alpha is 0 it holds `image` itself). background None: `image` as is."""
    from pathlib import Path

    from render.io import write_bytes_atomic

    image, alpha = _to_float(image, alpha)
    if background is not None:
        backdrop = _backdrop(image, alpha, background)
        a = alpha[..., None]
        straight = _premultiplied(image, alpha, backdrop) / np.maximum(a, 1e-6)
        image = np.where(a >= 0.5 / 255, straight, image)
    rgba = np.concatenate([image[..., :3], alpha[..., None]], axis=2)
    rgba8 = (np.clip(rgba, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    ok, buf = cv2.imencode(".png", cv2.cvtColor(rgba8, cv2.COLOR_RGBA2BGRA))
    if not ok:
        raise SineError(f"cannot encode an RGBA image for {path}")
    write_bytes_atomic(Path(path), buf.tobytes())
