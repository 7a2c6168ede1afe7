"""The proxy mesh: TSDF fusion of the depth maps (Open3D VoxelBlockGrid), cleaned for ARAP/embree.

Fusion: `o3d.t.geometry.VoxelBlockGrid` (ScalableTSDFVolume returns empty meshes for float depth
in Open3D 0.20). Closing: parts no view sees (the underside of an object on a turntable) leave
the fused surface open. With `closing_views` the visual hull (a closed outer bound) is ray cast
from virtual cameras all around the object (below and above included) and fused at low weight
(the real views are integrated `real_weight` times, each virtual view once), so the real depth
decides wherever it exists and the hull closes the rest: the mesh is watertight when the hull
is (the open faces of a partial capture's hull, recon.visual_hull, close nothing). (Open3D 0.20's `fill_holes` was found to corrupt vertices; it stays as a last, checked
step for small holes.) Cleaning: duplicated/degenerate triangles and vertices removed, non-manifold
edges removed, floaters culled (vertices that project outside the silhouettes of several views),
the largest connected component kept, quadric decimation to `target_triangles`, holes up to
`max_hole_edges` boundary edges closed by fans (`fill_small_holes`), normals oriented outward
(positive signed volume).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from tqdm import tqdm

from render.cameras import Camera
from render.errors import SineError


@dataclass
class ProxyParams:
    """How depth maps become the proxy (`build_proxy`); recon's proxy options."""

    voxel_size: float = 1 / 256  # TSDF voxel (run units; at least 1.5 pixel footprints)
    trunc_voxels: float = 3.0  # TSDF truncation in voxels
    target_triangles: int = 40_000  # quadric decimation target
    min_component: float = 0.02  # parts kept: >= this fraction of the largest's triangles


def build_proxy(
    cameras: list[Camera],
    depths: list[np.ndarray],
    masks: list[np.ndarray] | None,
    params: ProxyParams,
    closing: list[tuple[Camera, np.ndarray]] | None = None,
    carve: bool = False,
    progress: bool = True,
):
    """Depth maps [H, W] (camera z, 0 unknown) -> the cleaned proxy (legacy o3d mesh): TSDF
    fusion (`fuse_tsdf`, closed by `closing`, carved by the real views' free space with
    `carve`, which `sine recon` does by default; `progress`: its bar), floaters outside the
    masks culled (when masks are given), `clean_mesh`."""
    mesh = fuse_tsdf(
        cameras,
        depths,
        params.voxel_size,
        params.trunc_voxels,
        closing=closing,
        carve=carve,
        progress=progress,
    )
    if masks is not None:
        mesh = cull_outside_silhouettes(mesh, cameras, masks)
    return clean_mesh(mesh, params.target_triangles, min_component=params.min_component)


def closing_depths(
    vertices: np.ndarray, faces: np.ndarray, open_faces: np.ndarray | None = None
) -> list[tuple[Camera, np.ndarray]]:
    """A closed mesh (the visual hull, an earlier proxy) seen from `closing_views`: the
    (camera, depth) pairs `fuse_tsdf` closes unseen parts with. `open_faces` [F] bool: faces
    that bound nothing (an open visual hull) give no depth."""
    from recon.depth import HullMesh, bounded_depths, raycast_views

    virtual = closing_views()
    if open_faces is None:
        return list(zip(virtual, raycast_views(vertices, faces, virtual), strict=True))
    hull = HullMesh(vertices, faces, 0.0, open_faces)
    return list(zip(virtual, bounded_depths(hull, virtual), strict=True))


def closing_views(n: int = 26, distance: float = 3.0, size: int = 256) -> list[Camera]:
    """Virtual cameras around the origin (run units: object inside the unit sphere): the 26
    directions of a 3x3x3 cube's faces, edges and corners (`n` <= 26 takes the first n)."""
    from render.cameras import look_at

    dirs = [
        np.array([x, y, z], float)
        for x in (-1, 0, 1)
        for y in (-1, 0, 1)
        for z in (-1, 0, 1)
        if (x, y, z) != (0, 0, 0)
    ]
    dirs.sort(key=lambda d: np.abs(d).sum())  # faces first, then edges, corners
    f = 0.5 * size / np.tan(np.arcsin(1.0 / distance)) * 0.95
    cams = []
    for d in dirs[:n]:
        d = d / np.linalg.norm(d)
        up = np.array([0.0, 1.0, 0.0]) if abs(d[2]) > 0.9 else np.array([0.0, 0.0, 1.0])
        c2w = look_at(d * distance, np.zeros(3), up)
        cams.append(
            Camera(width=size, height=size, fx=f, fy=f, cx=size / 2, cy=size / 2,
                   camera_to_world=c2w, name="virtual")
        )  # fmt: skip
    return cams


def tsdf_voxel(cameras: list[Camera], voxel_size: float) -> float:
    """The voxel `fuse_tsdf` uses: at least 1.5 pixel footprints at the object (distance to
    the origin / fx), since finer voxels than the depth samples leave holes."""
    footprint = float(np.median([np.linalg.norm(c.center) / c.fx for c in cameras]))
    return max(voxel_size, 1.5 * footprint)


def fuse_tsdf(
    cameras: list[Camera],
    depths: list[np.ndarray],
    voxel_size: float = 1 / 128,
    trunc_voxels: float = 4.0,
    closing: list[tuple[Camera, np.ndarray]] | None = None,
    real_weight: int = 4,
    carve: bool = False,
    progress: bool = True,
):
    """TSDF-fuses float camera-z depth maps (run units) -> legacy o3d TriangleMesh.

    The voxel: `tsdf_voxel`. `closing`: (camera,
    depth) pairs fused once each while every real view is fused `real_weight` times.
    Depth 0 = unknown. `carve`: every block any view allocates is made first and the real views
    are integrated into all of them, so the free space in front of their surfaces erases what
    the closing views put there (a closing surface spanning a concavity the real depth sees
    into); real depth np.inf = seen empty (carves, never makes surface).
    """
    import open3d as o3d

    voxel_size = tsdf_voxel(cameras, voxel_size)

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
    real = [(cam, depth, True) for cam, depth in zip(cameras, depths, strict=True)]
    virtual = [(cam, depth, False) for cam, depth in closing or []]
    views = real * (real_weight if closing else 1) + virtual

    def geometry(cam, depth):
        """(K, extrinsic) as Open3D tensors for a depth map of cam's view."""
        K = cam.resized(depth.shape[1], depth.shape[0]).K - _half_pixel()
        ext = cam.world_to_camera
        return o3d.core.Tensor(K, o3d.core.float64), o3d.core.Tensor(ext, o3d.core.float64)

    def surface_blocks(cam, depth):
        """Block coordinates around the finite depth (None when there is none)."""
        d = np.where(np.isfinite(depth), depth, 0.0).astype(np.float32)
        if not (d > 0).any():
            return None
        image = o3d.t.geometry.Image(o3d.core.Tensor(d))
        K, ext = geometry(cam, d)
        depth_max = float(d.max()) * 1.01 + trunc
        return grid.compute_unique_block_coordinates(image, K, ext, 1.0, depth_max, trunc_voxels)

    if carve:  # every view's blocks first: the real views are integrated into all of them
        for cam, depth, _ in real + virtual:
            coords = surface_blocks(cam, np.asarray(depth, np.float32))
            if coords is not None:
                grid.hashmap().activate(coords)
        hashmap = grid.hashmap()
        all_blocks = hashmap.key_tensor()[hashmap.active_buf_indices().to(o3d.core.int64)]
    for cam, depth, is_real in tqdm(views, desc="tsdf", unit="view", disable=not progress):
        d = np.ascontiguousarray(depth, np.float32)
        if carve and is_real:
            if not (d > 0).any():
                continue
            coords = all_blocks
            d = np.where(np.isfinite(d), d, _FAR).astype(np.float32)
        else:
            coords = surface_blocks(cam, d)
            if coords is None:
                continue
            d = np.where(np.isfinite(d), d, 0.0).astype(np.float32)
        K, ext = geometry(cam, d)
        depth_max = float(d.max()) * 1.01 + trunc
        grid.integrate(
            coords, o3d.t.geometry.Image(o3d.core.Tensor(d)), K, ext, 1.0, depth_max, trunc_voxels
        )
    mesh = grid.extract_triangle_mesh(weight_threshold=1.0).to_legacy()
    return canonical_order(mesh)


def canonical_order(mesh):
    """`mesh` with its vertices sorted by position and its triangles by their vertices (each
    rotated to start at its smallest index, so the winding is kept). The fused mesh comes out of
    a hash map in an order that differs from run to run; in this order every later step (cleaning,
    decimation, sampling) gives the same result from the same captures."""
    import open3d as o3d

    verts, tris = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    order = np.lexsort(verts.T[::-1])  # by x, then y, then z
    rank = np.empty(len(order), np.int64)
    rank[order] = np.arange(len(order))
    tris = rank[tris]
    start = np.argmin(tris, axis=1)[:, None]  # [T, 1]
    tris = np.take_along_axis(tris, (start + np.arange(3)) % 3, axis=1)
    tris = tris[np.lexsort(tris.T[::-1])]
    out = o3d.geometry.TriangleMesh()
    out.vertices = o3d.utility.Vector3dVector(verts[order])
    out.triangles = o3d.utility.Vector3iVector(tris.astype(np.int32))
    return out


_FAR = 1e4  # depth standing for "seen empty" (np.inf) when carving: beyond every block


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
        row, col, inside, _ = cam.pixels_of(verts, m.shape)
        outside += (inside & ~m[row, col]).astype(np.int32)
    mesh.remove_vertices_by_mask(outside > max_outside)
    return mesh


def depth_disagreement(mesh, cameras: list[Camera], depths: list[np.ndarray]) -> np.ndarray:
    """|proxy - depth| along the ray [P] on every pixel where both exist: the mesh ray cast
    into each camera against its camera-z depth map [H, W] (0 or non-finite: unknown). With
    dataset depth this is the proxy's error; the fit's band (+-0.04) misses surface farther."""
    from render.raycast import MeshRaycaster

    caster = MeshRaycaster(mesh)
    errors = []
    for cam, depth in zip(cameras, depths, strict=True):
        origins, dirs = cam.rays()  # [P, 3] each, unit directions
        t_mesh = caster.cast(origins, dirs).t  # [P] along the ray, inf: no hit
        z = np.asarray(depth, np.float32).reshape(-1)  # [P] camera z
        t_depth = z / (dirs @ cam.camera_to_world[:3, 2])  # [P] along the ray
        both = np.isfinite(t_mesh) & np.isfinite(z) & (z > 0)
        errors.append(np.abs(t_mesh - t_depth)[both])
    return np.concatenate(errors)


def _keep_components(mesh, min_fraction: float):
    """Keeps connected components with >= min_fraction of the largest one's triangles."""
    clusters, counts, _ = mesh.cluster_connected_triangles()
    clusters, counts = np.asarray(clusters), np.asarray(counts)
    keep = np.flatnonzero(counts >= min_fraction * counts.max())
    mesh.remove_triangles_by_mask(~np.isin(clusters, keep))
    return mesh


def fill_small_holes(mesh, max_edges: int = 200):
    """Closes every boundary loop of at most `max_edges` edges with a fan around its centroid.

    Boundary half-edges (a -> b used by one triangle only) are grouped into loops (connected
    components); each gets a new vertex at the loop's centroid and the triangles (b, a, centre),
    which run against the neighbouring triangles' orientation as a closed surface needs.
    (Replaces Open3D 0.20's fill_holes, which was found to corrupt vertices.)
    """
    import open3d as o3d
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    tris = np.asarray(mesh.triangles)
    verts = np.asarray(mesh.vertices)
    if len(tris) == 0 or max_edges <= 0:
        return mesh
    half = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])  # [3F, 2]
    key = np.sort(half, axis=1)
    _, inverse, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    boundary = half[counts[inverse.ravel()] == 1]  # [B, 2] directed a -> b
    if len(boundary) == 0:
        return mesh
    n = len(verts)
    graph = coo_matrix((np.ones(len(boundary)), (boundary[:, 0], boundary[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    loop = label[boundary[:, 0]]
    new_verts, new_tris = [verts], [tris]
    next_index = n
    for lab in np.unique(loop):
        edges = boundary[loop == lab]
        if len(edges) > max_edges or len(edges) < 3:
            continue
        centre = verts[np.unique(edges)].mean(0)
        new_verts.append(centre[None])
        new_tris.append(np.stack([edges[:, 1], edges[:, 0], np.full(len(edges), next_index)], 1))
        next_index += 1
    if next_index == n:
        return mesh
    mesh.vertices = o3d.utility.Vector3dVector(np.concatenate(new_verts))
    mesh.triangles = o3d.utility.Vector3iVector(np.concatenate(new_tris).astype(np.int32))
    return mesh


def clean_mesh(
    mesh, target_triangles: int = 40_000, max_hole_edges: int = 200, min_component: float = 1.0
):
    """Components >= `min_component` x the largest (1 = largest only), no duplicates/degenerates/
    non-manifold edges, decimation, holes up to `max_hole_edges` filled, normals."""
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
    mesh = basic(fill_small_holes(mesh, max_hole_edges))
    if len(mesh.triangles) > target_triangles:
        mesh = basic(mesh.simplify_quadric_decimation(target_number_of_triangles=target_triangles))
    # quadric decimation can fling a vertex far away: drop such vertices.
    lo, hi = bounds
    v = np.asarray(mesh.vertices)
    mesh.remove_vertices_by_mask(np.any((v < lo) | (v > hi), axis=1))
    mesh = basic(_keep_components(basic(mesh), min_component))
    mesh = basic(fill_small_holes(mesh, max_hole_edges))  # holes the far-vertex drop opened
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
    """Size and topology of a proxy. `proxy_closed`: every edge has two faces and every vertex
    one fan (it bounds a volume); `proxy_watertight` (Open3D's) also asks for no
    self-intersection, which quadric decimation leaves in a few triangle pairs of most
    real proxies (harmless for ray casting and ARAP)."""
    return {
        "proxy_triangles": len(mesh.triangles),
        "proxy_vertices": len(mesh.vertices),
        "proxy_closed": bool(mesh.is_edge_manifold(False) and mesh.is_vertex_manifold()),
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
