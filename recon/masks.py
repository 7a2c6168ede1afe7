"""Automatic foreground masks for a plain backdrop, without network weights.

Per image: (1) the backdrop colours are estimated from the image border (k-means in CIE Lab: a
backdrop can be several colours, e.g. a blue turntable, a grey wall and black frame strips);
(2) colour keying: a pixel's distance to the nearest backdrop colour (Lab, lightness down-weighted
so shading of the backdrop matters less than its hue), thresholded by Otsu; (3) GrabCut (OpenCV)
initialised from the keying (sure background / probable / sure foreground); (4) morphological
cleanup, the largest connected components and small holes filled.

Masks that came with the capture (dataset masks or `--masks DIR`, copied by ingest) always win:
`compute_masks` only fills in the views that have none.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from render.errors import SineError
from render.io import read_image, read_mask, write_mask


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


def compute_masks(
    image_paths: list[Path],
    mask_paths: list[Path],
    params: MaskParams | None = None,
    redo: set[str] = frozenset(),
) -> dict:
    """Writes a mask for every image without one (or named in `redo`); returns per-view stats.

    Masks already present (from the dataset or `--masks`, copied by ingest) win and are kept; the
    pipeline passes in `redo` only the names of masks this stage made itself earlier (`--force`).
    Returns {"coverage": {name: fraction}, "auto": [names masked automatically]}.
    """
    coverage, auto = {}, []
    for image_path, mask_path in tqdm(
        list(zip(image_paths, mask_paths, strict=True)), desc="masks", unit="view"
    ):
        if mask_path.is_file() and image_path.name not in redo:
            mask = read_mask(mask_path)
        else:
            mask = segment_foreground(read_image(image_path), params)
            write_mask(mask_path, mask)
            auto.append(image_path.name)
        coverage[image_path.name] = float(mask.mean())
    empty = [name for name, c in coverage.items() if c == 0.0]
    if empty:
        raise SineError(
            f"empty foreground mask for {len(empty)} view(s) ({', '.join(empty[:5])}"
            f"{'...' if len(empty) > 5 else ''}): the object could not be separated from the backdrop. "
            "Give masks with --masks DIR, or photograph against a plain backdrop that differs in colour "
            "from the object"
        )
    return {"coverage": coverage, "auto": auto}
