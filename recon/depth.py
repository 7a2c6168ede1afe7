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
Partial captures (views that show the object cut by the image border): where the visual hull
is open (recon.visual_hull: no view bounds the object there) it gives no depth; stereo alone
fills what it can there (`stereo_open_pixel_fraction` of those pixels). The depth stage stops
with one message when too little of the masked pixels gets depth.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
from tqdm import tqdm

from recon.stereo import StereoParams, stereo_depth
from recon.visual_hull import carve_grid, hull_bounds, hull_mesh, open_faces, touches_border
from render.cameras import Camera
from render.raycast import MeshRaycaster


def raycast_depth(vertices: np.ndarray, faces: np.ndarray, cam: Camera) -> np.ndarray:
    """Camera-z depth [H, W] of a triangle mesh seen by `cam` (0 where no hit)."""
    return MeshRaycaster((vertices, faces)).depth(cam)


@dataclass
class HullMesh:
    """The visual hull as a closed mesh and where it is open (recon.visual_hull module doc)."""

    vertices: np.ndarray  # [V, 3]
    faces: np.ndarray  # [F, 3]
    voxel: float
    open_faces: np.ndarray  # [F] bool: no view bounds the object there
    complete_views: int = 0  # views whose mask stays clear of the image border

    @property
    def open_fraction(self) -> float:
        """Fraction of the hull's surface area that is open."""
        tri = self.vertices[self.faces]  # [F, 3, 3]
        area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
        return float(area[self.open_faces].sum() / max(area.sum(), 1e-12))

    def stats(self) -> dict:
        return {
            "hull_voxel_size": self.voxel,
            "hull_triangles": len(self.faces),
            "hull_open_fraction": round(self.open_fraction, 4),
            "hull_complete_views": self.complete_views,
        }


def read_hull(path) -> HullMesh | None:
    """The visual hull a recon saved (visual_hull.npz), or None where there is none."""
    if not Path(path).is_file():
        return None
    data = np.load(path)
    faces = data["faces"]
    open_faces = data["open_faces"] if "open_faces" in data else np.zeros(len(faces), bool)
    complete = int(data["complete_views"]) if "complete_views" in data else 0
    return HullMesh(data["vertices"], faces, float(data["voxel"]), open_faces, complete)


def visual_hull(
    cameras: list[Camera], masks: list[np.ndarray], resolution: int = 160, tolerance: int = 1
) -> HullMesh:
    """The visual hull carved at `resolution` voxels across its box (`hull_bounds`), meshed."""
    lo, hi = hull_bounds(cameras, masks)
    # `tolerance` views may disagree: one bad mask must not cut a thin part off everywhere.
    occ, carved, origin, voxel = carve_grid(
        cameras, masks, lo, hi, resolution, dilate_px=1, tolerance=tolerance
    )
    verts, faces = hull_mesh(occ, origin, voxel)
    return HullMesh(
        verts,
        faces,
        voxel,
        open_faces(verts, faces, occ, carved, origin, voxel),
        complete_views=sum(not touches_border(m) for m in masks),
    )


def visual_hull_mesh(
    cameras: list[Camera], masks: list[np.ndarray], resolution: int = 160, tolerance: int = 1
) -> tuple[np.ndarray, np.ndarray, float]:
    """The visual hull as a closed mesh: vertices [V, 3], faces [F, 3], voxel size."""
    hull = visual_hull(cameras, masks, resolution, tolerance)
    return hull.vertices, hull.faces, hull.voxel


def raycast_views(vertices: np.ndarray, faces: np.ndarray, cameras: list[Camera]):
    """Camera-z depth [H, W] of the mesh in every camera (0 = no hit)."""
    caster = MeshRaycaster((vertices, faces))
    return [caster.depth(cam) for cam in cameras]


def bounded_depths(hull: HullMesh, cameras: list[Camera]) -> list[np.ndarray]:
    """Camera-z depth [H, W] of the hull in every camera, 0 where the first hit is open."""
    caster = MeshRaycaster((hull.vertices, hull.faces))
    out = []
    for cam in cameras:
        origins, dirs = cam.rays()
        hits = caster.cast(origins, dirs)
        z = hits.t * (dirs @ cam.camera_to_world[:3, 2].astype(np.float32))  # [H*W]
        tri = np.asarray(hits.triangle)
        z[~np.isfinite(z) | ((tri >= 0) & hull.open_faces[np.maximum(tri, 0)])] = 0.0
        out.append(z.reshape(cam.height, cam.width).astype(np.float32))
    return out


def visual_hull_depth(
    cameras: list[Camera],
    masks: list[np.ndarray],
    resolution: int = 160,
    tolerance: int = 1,
    hull: HullMesh | None = None,
) -> tuple[list[np.ndarray], dict]:
    """Depth maps of the visual hull for every view (masked; 0 where the hull is open), and
    stats (`hull_open_pixel_fraction`: of the masked pixels, those the hull gives no depth)."""
    hull = hull or visual_hull(cameras, masks, resolution, tolerance)
    depths = bounded_depths(hull, cameras)
    for z, mask in tqdm(list(zip(depths, masks, strict=True)), desc="hull depth", unit="view"):
        z[~mask] = 0.0
    masked = sum(int(m.sum()) for m in masks)
    missing = sum(int((m & (z <= 0)).sum()) for z, m in zip(depths, masks, strict=True))
    return depths, {
        "hull_resolution": resolution,
        **hull.stats(),
        "hull_open_pixel_fraction": missing / max(masked, 1),
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
    """Visual-hull depth with stereo where it is consistent (see the module docstring); inside
    the mask where the hull gives no depth (it is open there), stereo alone."""
    out, used, total, unknown_total, unknown_used = [], 0, 0, 0, 0
    for i, hull in enumerate(tqdm(hull_depths, desc="stereo depth", unit="view")):
        z = hull[hull > 0]
        unknown = masks[i] & (hull <= 0)
        if len(z) == 0:
            out.append(hull)
            unknown_total += int(unknown.sum())
            continue
        z_min, z_max = float(z.min()), float(z.max()) + max_behind
        stereo = stereo_depth(cameras, images, masks, i, (z_min, z_max), params, agree=front_tol)
        fused, use = fuse_hull_stereo(hull, stereo, front_tol, max_behind)
        if unknown.any():  # the object may go on beyond the hull: search further, there only
            # (a separate pass: the wider disparity range may be more than SGBM takes, which
            # must not cost the hull's pixels their stereo)
            span = z_max - z_min
            wide = (max(z_min - span, 0.2 * z_min), z_max + span)
            stereo = stereo_depth(cameras, images, masks, i, wide, params, agree=front_tol)
        fill = unknown & (stereo > 0)
        fused[fill] = stereo[fill]
        out.append(fused)
        used += int(use.sum())
        total += int((hull > 0).sum())
        unknown_total += int(unknown.sum())
        unknown_used += int(fill.sum())
    return out, {
        "stereo_pixel_fraction": used / max(total, 1),
        "stereo_open_pixel_fraction": unknown_used / max(unknown_total, 1),
        "stereo_front_tolerance": front_tol,
        "stereo_max_behind": max_behind,
    }
