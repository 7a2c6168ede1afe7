"""Per-view depth maps (depth/<stem>.npy, float32 camera z in run units, 0 = none).

Sources (the one used is written to recon_report.json as `depth_source`; `depth_method` of
`sine recon` chooses; "auto" = "dataset" when every view has depth, else "visual_hull+stereo",
which measured better than the hull alone: bench/RESULTS.md, Reconstruction):
- "dataset": every view already has depth from the capture (copied by ingest; rescaled into the
  run frame when the poses/normalisation changed units) -> kept as it is.
- "visual_hull": the visual hull is carved from all masks + cameras at `resolution` voxels
  across, meshed by marching cubes and ray cast into every view (render.raycast), depth kept
  inside the view's mask. It is exact on the silhouette and an outer bound elsewhere: it misses
  concavities that no silhouette reveals.
- "visual_hull+stereo": the hull depth, replaced per pixel by two-view stereo (recon/stereo.py:
  rectified StereoSGBM with the nearest neighbour on each side, left-right checked, the two
  neighbours agreeing) where stereo is consistent with the hull: not in front of the hull
  surface (beyond `front_tol`, the hull is an outer bound) and at most `max_behind` behind it
  (a concavity, not a mismatch). The hull is kept everywhere else. The report says which
  fraction of the masked pixels took stereo (`stereo_pixel_fraction`).
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from recon.stereo import StereoParams, stereo_depth
from recon.visual_hull import carve, hull_bounds, hull_mesh
from render.cameras import Camera
from render.raycast import MeshRaycaster


def raycast_depth(vertices: np.ndarray, faces: np.ndarray, cam: Camera) -> np.ndarray:
    """Camera-z depth [H, W] of a triangle mesh seen by `cam` (0 where no hit)."""
    return MeshRaycaster((vertices, faces)).depth(cam)


def visual_hull_mesh(
    cameras: list[Camera], masks: list[np.ndarray], resolution: int = 160, tolerance: int = 1
) -> tuple[np.ndarray, np.ndarray, float]:
    """The visual hull as a closed mesh: vertices [V, 3], faces [F, 3], voxel size."""
    lo, hi = hull_bounds(cameras, masks)
    # `tolerance` views may disagree: one bad mask must not cut a thin part off everywhere.
    occ, origin, voxel = carve(cameras, masks, lo, hi, resolution, dilate_px=1, tolerance=tolerance)
    verts, faces = hull_mesh(occ, origin, voxel)
    return verts, faces, voxel


def raycast_views(vertices: np.ndarray, faces: np.ndarray, cameras: list[Camera]):
    """Camera-z depth [H, W] of the mesh in every camera (0 = no hit)."""
    caster = MeshRaycaster((vertices, faces))
    return [caster.depth(cam) for cam in cameras]


def visual_hull_depth(
    cameras: list[Camera],
    masks: list[np.ndarray],
    resolution: int = 160,
    tolerance: int = 1,
    hull: tuple[np.ndarray, np.ndarray, float] | None = None,
) -> tuple[list[np.ndarray], dict]:
    """Depth maps of the visual hull for every view (masked), and stats."""
    verts, faces, voxel = hull or visual_hull_mesh(cameras, masks, resolution, tolerance)
    depths = raycast_views(verts, faces, cameras)
    for z, mask in tqdm(list(zip(depths, masks, strict=True)), desc="hull depth", unit="view"):
        z[~mask] = 0.0
    return depths, {
        "hull_resolution": resolution,
        "hull_voxel_size": voxel,
        "hull_triangles": len(faces),
    }


def fuse_hull_stereo(
    hull: np.ndarray, stereo: np.ndarray, front_tol: float, max_behind: float
) -> tuple[np.ndarray, np.ndarray]:
    """Per pixel: stereo where hull - front_tol <= stereo <= hull + max_behind, else the hull.

    Returns the fused depth [H, W] and the bool map [H, W] of pixels that took stereo.
    """
    use = (hull > 0) & (stereo > 0) & (stereo >= hull - front_tol) & (stereo <= hull + max_behind)
    return np.where(use, stereo, hull).astype(np.float32), use


def hull_stereo_depth(
    cameras: list[Camera],
    images: list[np.ndarray],
    masks: list[np.ndarray],
    hull_depths: list[np.ndarray],
    front_tol: float,
    max_behind: float,
    params: StereoParams | None = None,
) -> tuple[list[np.ndarray], dict]:
    """Visual-hull depth with stereo where it is consistent (see the module docstring)."""
    out, used, total = [], 0, 0
    for i, hull in enumerate(tqdm(hull_depths, desc="stereo depth", unit="view")):
        z = hull[hull > 0]
        if len(z) == 0:
            out.append(hull)
            continue
        z_range = (float(z.min()), float(z.max()) + max_behind)
        stereo = stereo_depth(cameras, images, masks, i, z_range, params, agree=front_tol)
        fused, use = fuse_hull_stereo(hull, stereo, front_tol, max_behind)
        out.append(fused)
        used += int(use.sum())
        total += int((hull > 0).sum())
    return out, {
        "stereo_pixel_fraction": used / max(total, 1),
        "stereo_front_tolerance": front_tol,
        "stereo_max_behind": max_behind,
    }
