"""Where the recon measured its proxy: for each proxy vertex, the share of the views that see
it in which the recon's depth there was the visual hull's alone, not stereo's. The fit starts
its band wide only there (`recon.fit_proxy.band_at_round`): the hull is an outer bound, the surface
may lie well inside it, while stereo put a measured point where it is.

Which pixels took stereo is read back from the run itself: the recon's depth map differs from
the depth of its visual hull (visual_hull.npz, ray cast as the recon did) exactly where
stereo replaced it (`recon.depth.fuse_hull_stereo`) or filled a pixel the hull leaves open.
"""

from __future__ import annotations

import numpy as np

from recon.depth import bounded_depths, read_hull
from recon.rundir import RunDir
from render.io import read_depth
from render.raycast import MeshRaycaster


def stereo_pixels(run: RunDir) -> tuple[list, float] | None:
    """([(camera, took_stereo [H, W] bool)] of every view with a depth map, hull voxel size),
    or None without the recon's visual hull."""
    hull = read_hull(run.root / "visual_hull.npz")
    if hull is None:
        return None
    cams = [c for c in run.load_cameras().frames if run.depth_path(c.name).is_file()]
    out = []
    for cam, hull_z in zip(cams, bounded_depths(hull, cams), strict=True):
        depth = read_depth(run.depth_path(cam.name))
        if depth.shape != hull_z.shape:
            continue
        same = np.isclose(depth, hull_z, rtol=1e-5, atol=0.0)
        out.append((cam, (depth > 0) & ~same))
    return out, hull.voxel


def unmeasured_share(stereo: tuple[list, float], vertices: np.ndarray, faces: np.ndarray):
    """Per vertex of a proxy mesh (vertices [V, 3], faces [F, 3]) in [0, 1] [V]: of the views
    in which it is visible (the proxy's first hit on the ray to it is the vertex itself, to
    half a hull voxel), the share whose depth at its pixel was the hull's alone (`stereo`:
    what `stereo_pixels` found); 1 where no view sees it."""
    views, voxel = stereo
    caster = MeshRaycaster((vertices, faces))
    seen = np.zeros(len(vertices))
    measured = np.zeros(len(vertices))
    for cam, took_stereo in views:
        row, col, inside, _ = cam.pixels_of(vertices)  # [V] each
        offset = vertices - cam.center  # [V, 3]
        distance = np.linalg.norm(offset, axis=1)
        dirs = offset / np.maximum(distance, 1e-12)[:, None]
        origins = np.broadcast_to(cam.center, offset.shape)
        first = caster.cast(origins, dirs).t  # [V] the proxy's first hit towards each vertex
        visible = inside & (first > distance - 0.5 * voxel)
        seen += visible
        measured += visible & took_stereo[row, col]
    return np.where(seen > 0, 1.0 - measured / np.maximum(seen, 1), 1.0).astype(np.float32)
