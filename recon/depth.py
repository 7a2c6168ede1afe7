"""Per-view depth maps (depth/<stem>.npy, float32 camera z in run units, 0 = none).

Sources, best first (the one used is written to recon_report.json as `depth_source`):
- "dataset": every view already has depth from the capture (copied by ingest; rescaled into the
  run frame when the poses/normalisation changed units) -> kept as it is.
- "visual_hull": otherwise the visual hull is carved from all masks + cameras at `resolution`
  voxels across, meshed by marching cubes and ray cast into every view (Open3D), depth kept
  inside the view's mask. It is exact on the silhouette and an outer bound elsewhere: it misses
  concavities that no silhouette reveals. (Stereo between neighbouring views to recover them
  is not implemented yet.)
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from recon.visual_hull import carve, hull_bounds, hull_mesh
from render.cameras import Camera


def raycast_depth(vertices: np.ndarray, faces: np.ndarray, cam: Camera) -> np.ndarray:
    """Camera-z depth [H, W] of a triangle mesh seen by `cam` (0 where no hit)."""
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(vertices, np.float32)),
        o3d.core.Tensor(np.asarray(faces, np.uint32)),
    )
    return _cast(scene, cam)


def _cast(scene, cam: Camera) -> np.ndarray:
    import open3d as o3d

    origins, dirs = cam.rays()  # [H*W, 3] each
    rays = o3d.core.Tensor(np.concatenate([origins, dirs], 1).astype(np.float32))
    t = scene.cast_rays(rays)["t_hit"].numpy()  # [H*W], inf = miss
    forward = cam.camera_to_world[:3, 2].astype(np.float32)
    z = t * (dirs @ forward)
    z[~np.isfinite(z)] = 0.0
    return z.reshape(cam.height, cam.width).astype(np.float32)


def visual_hull_depth(
    cameras: list[Camera], masks: list[np.ndarray], resolution: int = 160, tolerance: int = 1
) -> tuple[list[np.ndarray], dict]:
    """Depth maps of the visual hull for every view (masked), and stats."""
    import open3d as o3d

    lo, hi = hull_bounds(cameras, masks)
    # `tolerance` views may disagree: one bad mask must not cut a thin part off everywhere.
    occ, origin, voxel = carve(cameras, masks, lo, hi, resolution, dilate_px=1, tolerance=tolerance)
    verts, faces = hull_mesh(occ, origin, voxel)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(verts.astype(np.float32)), o3d.core.Tensor(faces.astype(np.uint32))
    )
    depths = []
    for cam, mask in tqdm(list(zip(cameras, masks, strict=True)), desc="hull depth", unit="view"):
        z = _cast(scene, cam)
        z[~mask] = 0.0
        depths.append(z)
    return depths, {
        "hull_resolution": resolution,
        "hull_voxel_size": voxel,
        "hull_triangles": len(faces),
    }
