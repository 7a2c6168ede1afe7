"""The proxy mesh: TSDF fusion of the depth maps (Open3D VoxelBlockGrid), cleaned for ARAP/embree.

Fusion: `o3d.t.geometry.VoxelBlockGrid` (ScalableTSDFVolume returns empty meshes for float depth
in Open3D 0.20). Cleaning: duplicated/degenerate triangles and vertices removed, non-manifold
edges removed, floaters culled (vertices that project outside the silhouettes of several views),
the largest connected component kept, small holes filled, quadric decimation to
`target_triangles`, normals oriented outward (positive signed volume).
"""

from __future__ import annotations

import numpy as np
from tqdm import tqdm

from render.cameras import Camera
from render.errors import SineError


def fuse_tsdf(
    cameras: list[Camera],
    depths: list[np.ndarray],
    voxel_size: float = 1 / 128,
    trunc_voxels: float = 4.0,
):
    """TSDF-fuses float camera-z depth maps (run units) -> legacy o3d TriangleMesh.

    The voxel is at least 1.5 pixel footprints at the object (distance to the origin / fx): finer
    voxels than the depth samples leave the fused surface full of holes.
    """
    import open3d as o3d

    footprint = float(np.median([np.linalg.norm(c.center) / c.fx for c in cameras]))
    voxel_size = max(voxel_size, 1.5 * footprint)

    device = o3d.core.Device("CPU:0")
    grid = o3d.t.geometry.VoxelBlockGrid(
        attr_names=("tsdf", "weight"),
        attr_dtypes=(o3d.core.float32, o3d.core.float32),
        attr_channels=((1), (1)),
        voxel_size=voxel_size,
        block_resolution=8,
        block_count=100_000,
        device=device,
    )
    trunc_voxels = float(trunc_voxels)
    trunc = trunc_voxels * voxel_size
    for cam, depth in tqdm(list(zip(cameras, depths, strict=True)), desc="tsdf", unit="view"):
        d = np.ascontiguousarray(depth, np.float32)
        if not (d > 0).any():
            continue
        depth_t = o3d.t.geometry.Image(o3d.core.Tensor(d))
        K = o3d.core.Tensor(cam.resized(d.shape[1], d.shape[0]).K - _half_pixel(), o3d.core.float64)
        ext = o3d.core.Tensor(cam.world_to_camera, o3d.core.float64)
        depth_max = float(d.max()) * 1.01 + trunc
        coords = grid.compute_unique_block_coordinates(
            depth_t, K, ext, 1.0, depth_max, trunc_voxels
        )
        grid.integrate(coords, depth_t, K, ext, 1.0, depth_max, trunc_voxels)
    mesh = grid.extract_triangle_mesh(weight_threshold=1.0).to_legacy()
    return mesh


def _half_pixel() -> np.ndarray:
    """Open3D puts pixel centres at integer coordinates, we at +0.5: shift the principal point."""
    out = np.zeros((3, 3))
    out[0, 2] = out[1, 2] = 0.5
    return out


def cull_outside_silhouettes(
    mesh, cameras: list[Camera], masks: list[np.ndarray], max_outside: int = 1
):
    """Removes vertices that fall outside the (dilated) masks of more than `max_outside` views."""
    import cv2

    verts = np.asarray(mesh.vertices)
    outside = np.zeros(len(verts), np.int32)
    for cam, mask in zip(cameras, masks, strict=True):
        m = cv2.dilate(mask.astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        uv, z = cam.project(verts)
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (z > 0) & (col >= 0) & (col < m.shape[1]) & (row >= 0) & (row < m.shape[0])
        fg = np.zeros(len(verts), bool)
        fg[inside] = m[row[inside], col[inside]]
        outside += (inside & ~fg).astype(np.int32)
    mesh.remove_vertices_by_mask(outside > max_outside)
    return mesh


def _keep_components(mesh, min_fraction: float):
    """Keeps connected components with >= min_fraction of the largest one's triangles."""
    clusters, counts, _ = mesh.cluster_connected_triangles()
    clusters, counts = np.asarray(clusters), np.asarray(counts)
    keep = np.flatnonzero(counts >= min_fraction * counts.max())
    mesh.remove_triangles_by_mask(~np.isin(clusters, keep))
    return mesh


def clean_mesh(
    mesh, target_triangles: int = 40_000, hole_size: float = 0.1, min_component: float = 1.0
):
    """Components >= `min_component` x the largest (1 = largest only), no duplicates/degenerates/non-manifold edges, holes, decimation, normals."""
    import open3d as o3d

    def basic(m):
        m.remove_duplicated_vertices()
        m.remove_duplicated_triangles()
        m.remove_degenerate_triangles()
        m.remove_non_manifold_edges()
        m.remove_unreferenced_vertices()
        return m

    mesh = basic(mesh)
    v = np.asarray(mesh.vertices)
    span = v.max(0) - v.min(0) if len(v) else np.zeros(3)
    bounds = (v.min(0) - 0.05 * span, v.max(0) + 0.05 * span) if len(v) else (0, 0)
    if len(mesh.triangles) == 0:
        raise SineError(
            "the fused proxy mesh is empty: the depth maps do not agree (check poses and masks)"
        )
    mesh = basic(_keep_components(mesh, min_component))
    try:
        filled = (
            o3d.t.geometry.TriangleMesh.from_legacy(mesh)
            .fill_holes(hole_size=hole_size)
            .to_legacy()
        )
        # fill_holes (Open3D 0.20) can overwrite a vertex with garbage (~1e36): then skip it.
        old, new = np.asarray(mesh.vertices), np.asarray(filled.vertices)
        if len(new) == len(old) and np.allclose(new, old):
            mesh = basic(filled)
    except Exception:  # noqa: BLE001 - hole filling is best effort
        pass
    if len(mesh.triangles) > target_triangles:
        mesh = basic(mesh.simplify_quadric_decimation(target_number_of_triangles=target_triangles))
    # hole filling and quadric decimation can fling a vertex far away: drop such vertices.
    lo, hi = bounds
    v = np.asarray(mesh.vertices)
    mesh.remove_vertices_by_mask(np.any((v < lo) | (v > hi), axis=1))
    mesh = basic(_keep_components(basic(mesh), min_component))
    if signed_volume(mesh) < 0:
        mesh.triangles = o3d.utility.Vector3iVector(np.asarray(mesh.triangles)[:, ::-1].copy())
    mesh.compute_vertex_normals()
    return mesh


def signed_volume(mesh) -> float:
    v = np.asarray(mesh.vertices)
    f = np.asarray(mesh.triangles)
    if len(f) == 0:
        return 0.0
    a, b, c = v[f[:, 0]], v[f[:, 1]], v[f[:, 2]]
    return float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)


def mesh_stats(mesh) -> dict:
    return {
        "proxy_triangles": len(mesh.triangles),
        "proxy_vertices": len(mesh.vertices),
        "proxy_watertight": bool(mesh.is_watertight()),
        "proxy_edge_manifold": bool(mesh.is_edge_manifold()),
        "proxy_vertex_manifold": bool(mesh.is_vertex_manifold()),
        "proxy_volume": signed_volume(mesh),
    }


def write_mesh(path, mesh) -> None:
    import open3d as o3d

    from render.io import atomic_path

    with atomic_path(path) as tmp:
        if not o3d.io.write_triangle_mesh(str(tmp), mesh, write_ascii=False):
            raise SineError(f"could not write {path}")
