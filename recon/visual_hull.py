"""Visual hull: voxel carving from foreground masks and calibrated cameras.

A voxel is kept when every view that sees it (projects inside the image, in front of the camera)
has foreground there (masks slightly dilated against calibration/mask errors; `tolerance` views
may disagree). Partial and handheld captures: a view whose mask touches the image border shows
the object cut by its frame, so it says nothing about what lies outside the frame; a view whose
mask stays clear of the border shows the whole object ("complete"), so it also carves what lies
outside its frame or behind it. Space that no view bounds is not the object: unless at least
two complete views bound every voxel, a voxel must be seen by `min_seen_fraction` of the views
(complete views see every voxel). The hull's surface is "open" where an empty neighbour was
left empty for that reason (or lies outside the carved box) rather than carved by a view: there
the object may go on, and the hull is no bound (`Hull.open_faces`; the depth stage takes stereo
there and the proxy is not closed with those faces).
Used by normalisation (the object's bounding sphere), the self-checks and as a depth source
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


def touches_border(mask: np.ndarray) -> bool:
    """The mask [H, W] has foreground on the image's outermost rows or columns."""
    return bool(mask[0].any() or mask[-1].any() or mask[:, 0].any() or mask[:, -1].any())


def carve_grid(
    cameras: list[Camera],
    masks: list[np.ndarray],
    lo: np.ndarray,
    hi: np.ndarray,
    resolution: int,
    dilate_px: int = 1,
    tolerance: int = 0,
    min_seen_fraction: float = 0.5,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """`carve`, plus the voxels [R, R, R] bool that views carved (the rest of the empty ones
    were left empty because too few views see them): (occupancy, carved, origin, voxel)."""
    lo, hi = np.asarray(lo, np.float64), np.asarray(hi, np.float64)
    voxel = float((hi - lo).max() / resolution)
    dims = np.maximum(1, np.ceil((hi - lo) / voxel).astype(int))
    origin = lo + 0.5 * voxel
    axes = [origin[i] + voxel * np.arange(dims[i]) for i in range(3)]
    grid = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)  # [V, 3]
    alive = np.arange(len(grid))
    misses = np.zeros(len(grid), np.int32)
    seen = np.zeros(len(grid), np.int32)
    prepared = _prepare_masks(masks, dilate_px)
    complete = [not touches_border(m) for m in prepared]
    for cam, mask, whole in zip(cameras, prepared, complete, strict=True):
        pts = grid[alive]
        row, col, inside, _ = cam.pixels_of(pts, mask.shape)
        fg = inside & mask[row, col]
        judged = np.ones(len(alive), bool) if whole else inside  # complete: outside = empty
        misses[alive[judged & ~fg]] += 1
        seen[alive[judged]] += 1
        alive = alive[misses[alive] <= tolerance]
        if len(alive) == 0:
            break
    carved = misses > tolerance
    if sum(complete) < 2:  # space that most views do not see at all is not the object
        need = max(1, int(np.ceil(min_seen_fraction * len(cameras))))
        alive = alive[seen[alive] >= need]
    occ = np.zeros(len(grid), bool)
    occ[alive] = True
    return occ.reshape(dims), carved.reshape(dims), origin, voxel


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
    """Occupancy [R, R, R] (x, y, z index order) of the cube-ish box [lo, hi] (module doc).

    Returns (occupancy, origin = centre of voxel (0, 0, 0), voxel size). The box is made cubic
    with its longest side split into `resolution` voxels.
    """
    occ, _, origin, voxel = carve_grid(
        cameras, masks, lo, hi, resolution, dilate_px, tolerance, min_seen_fraction
    )
    return occ, origin, voxel


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


class UnboundedHull(SineError):
    """The views do not bound the object: every point inside all silhouettes is seen by too
    few views (a partial capture: close-ups, the object cut by the image border)."""


def hull_bounds(
    cameras: list[Camera], masks: list[np.ndarray], resolution: int = 64, dilate_px: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """Tight box [lo, hi] of the visual hull (coarse carve of the region the cameras look at,
    then a second carve in the found box, padded by two voxels). An empty hull raises
    SineError: `UnboundedHull` when the views agree on some space but see none of it often
    enough (a partial capture), else the masks and cameras disagree."""
    target, half = object_region(cameras)
    lo, hi = target - half, target + half
    for _ in range(2):
        occ, carved, origin, voxel = carve_grid(
            cameras, masks, lo, hi, resolution, dilate_px=dilate_px, tolerance=1
        )
        idx = np.argwhere(occ)
        if len(idx) == 0:
            cut = sum(touches_border(m) for m in masks)
            if not carved.all():
                raise UnboundedHull(
                    f"the views do not bound the object: the space inside every silhouette is "
                    f"seen by fewer than half of the {len(masks)} views ({cut} show the object "
                    f"cut by the image border, {len(masks) - cut} show it whole), so the visual "
                    "hull is empty. Try: add views that show the whole object (at least two, "
                    "from different sides), or overlapping views all around it"
                )
            raise SineError(
                f"the visual hull is empty: the masks and cameras disagree (no 3D point is inside "
                f"the silhouettes of all {len(masks)} views, even with one view allowed to "
                f"disagree; {cut} of them show the object cut by the image border). Check masks/ "
                "in the run directory (masks that miss the object or cover the background) and "
                "the poses (the self-check in recon_report.json)"
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


def open_faces(
    vertices: np.ndarray,
    faces: np.ndarray,
    occ: np.ndarray,
    carved: np.ndarray,
    origin: np.ndarray,
    voxel: float,
) -> np.ndarray:
    """Per face of `hull_mesh(occ, ...)` [F] bool: the face is open (module doc), i.e. the
    empty voxel beside each of its vertices was not carved by a view or lies outside the grid."""
    idx = (np.asarray(vertices) - origin) / voxel  # [V, 3] grid coordinates, one axis at k + 0.5
    frac = idx - np.floor(idx)
    axis = np.argmax(np.abs(frac - np.round(frac)), axis=1)  # the non-integer coordinate
    rows = np.arange(len(idx))
    lo = np.round(idx).astype(np.int64)
    lo[rows, axis] = np.floor(idx[rows, axis]).astype(np.int64)
    hi = lo.copy()
    hi[rows, axis] += 1
    dims = np.array(occ.shape)

    def lookup(grid: np.ndarray, ijk: np.ndarray, outside: bool) -> np.ndarray:
        ok = np.all((ijk >= 0) & (ijk < dims), axis=1)
        out = np.full(len(ijk), outside)
        out[ok] = grid[ijk[ok, 0], ijk[ok, 1], ijk[ok, 2]]
        return out

    empty = np.where(lookup(occ, lo, False)[:, None], hi, lo)  # [V, 3] the empty side
    vertex_open = ~lookup(carved, empty, False)
    return vertex_open[faces].all(axis=1)
