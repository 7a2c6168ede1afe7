"""Visual hull: voxel carving from foreground masks and calibrated cameras.

A voxel is kept when every view that sees it (projects inside the image, in front of the camera)
has foreground there (masks slightly dilated against calibration/mask errors; `tolerance` views
may disagree) and at least `min_seen_fraction` of the views see it. Used by normalisation (the object's bounding sphere) and as a depth source
(hull mesh via marching cubes, rendered by ray casting).
"""

from __future__ import annotations

import cv2
import numpy as np

from render.cameras import Camera
from render.errors import SineError


def _prepare_masks(masks: list[np.ndarray], dilate_px: int) -> list[np.ndarray]:
    if dilate_px <= 0:
        return [m.astype(bool) for m in masks]
    k = np.ones((2 * dilate_px + 1, 2 * dilate_px + 1), np.uint8)
    return [cv2.dilate(m.astype(np.uint8), k) > 0 for m in masks]


def carve(
    cameras: list[Camera],
    masks: list[np.ndarray],
    lo: np.ndarray,
    hi: np.ndarray,
    resolution: int,
    dilate_px: int = 1,
    tolerance: int = 0,
    min_seen_fraction: float = 0.5,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Occupancy [R, R, R] (x, y, z index order) of the cube-ish box [lo, hi].

    Returns (occupancy, origin = centre of voxel (0, 0, 0), voxel size). The box is made cubic
    with its longest side split into `resolution` voxels.
    """
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    voxel = float((hi - lo).max() / resolution)
    dims = np.maximum(1, np.ceil((hi - lo) / voxel).astype(int))
    origin = lo + 0.5 * voxel
    axes = [origin[i] + voxel * np.arange(dims[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # [V, 3]
    alive = np.arange(len(grid))
    misses = np.zeros(len(grid), np.int32)
    seen = np.zeros(len(grid), np.int32)
    for cam, mask in zip(cameras, _prepare_masks(masks, dilate_px), strict=True):
        pts = grid[alive]
        uv, z = cam.project(pts)
        h, w = mask.shape
        sx, sy = w / cam.width, h / cam.height
        col = np.floor(uv[:, 0] * sx).astype(np.int64)
        row = np.floor(uv[:, 1] * sy).astype(np.int64)
        inside = (z > 0) & (col >= 0) & (col < w) & (row >= 0) & (row < h)
        fg = np.zeros(len(alive), bool)
        fg[inside] = mask[row[inside], col[inside]]
        miss = inside & ~fg
        misses[alive[miss]] += 1
        seen[alive[inside]] += 1
        alive = alive[misses[alive] <= tolerance]
        if len(alive) == 0:
            break
    # space that most views do not see at all is not the object (nothing bounds it there).
    alive = alive[seen[alive] >= max(1, int(np.ceil(min_seen_fraction * len(cameras))))]
    occ = np.zeros(len(grid), bool)
    occ[alive] = True
    return occ.reshape(dims), origin, voxel


def object_region(cameras: list[Camera]) -> tuple[np.ndarray, float]:
    """A point the cameras look at (least squares to all optical axes) and a box half-size that
    holds everything visible near it."""
    A, b = np.zeros((3, 3)), np.zeros(3)
    for cam in cameras:
        d = cam.camera_to_world[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ cam.center
    target = np.linalg.lstsq(A, b, rcond=None)[0]
    dists = np.array([np.linalg.norm(c.center - target) for c in cameras])
    half_fov = max(max(c.width / (2 * c.fx), c.height / (2 * c.fy)) for c in cameras)
    return target, float(np.median(dists) * half_fov * 1.2)


def hull_bounds(
    cameras: list[Camera], masks: list[np.ndarray], resolution: int = 64, dilate_px: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Tight box [lo, hi] of the visual hull (coarse carve of the region the cameras look at,
    then a second carve in the found box, padded by two voxels)."""
    target, half = object_region(cameras)
    lo, hi = target - half, target + half
    for _ in range(2):
        occ, origin, voxel = carve(
            cameras, masks, lo, hi, resolution, dilate_px=dilate_px, tolerance=1
        )
        idx = np.argwhere(occ)
        if len(idx) == 0:
            raise SineError(
                "the visual hull is empty: the masks and cameras disagree (no 3D point is inside "
                "every silhouette). Check masks/ and the poses"
            )
        lo = origin + (idx.min(0) - 2.0) * voxel
        hi = origin + (idx.max(0) + 2.0) * voxel
    return lo, hi


def hull_mesh(occ: np.ndarray, origin: np.ndarray, voxel: float) -> tuple[np.ndarray, np.ndarray]:
    """Marching cubes of the occupancy (padded so the surface closes): vertices [V, 3], faces [F, 3]."""
    from skimage.measure import marching_cubes

    padded = np.pad(occ.astype(np.float32), 1)
    verts, faces, _, _ = marching_cubes(padded, level=0.5)
    verts = origin + (verts - 1.0) * voxel
    return verts, faces.astype(np.int64)
