"""The mesh ray caster: hand-computed hits, moved vertices, cameras, multiple hits, and the
Open3D and embree backends agreeing on a real mesh."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch
import trimesh

from render.cameras import Camera, look_at
from render.raycast import MeshRaycaster, mesh_arrays

BACKENDS = ("open3d", "embree")
SPOT = Path(__file__).resolve().parents[1].parent / "shared/data/meshes/spot/spot_triangulated.obj"


def _triangle():
    v = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0]])  # normal +z
    return v, np.array([[0, 1, 2]])


def _unit_cube():
    box = trimesh.creation.box(extents=(1.0, 1.0, 1.0))  # outward winding
    return np.asarray(box.vertices) + 0.5, np.asarray(box.faces)  # [0, 1]^3


def _random_rays(n: int, seed: int = 0, radius: float = 3.0, spread: float = 0.7):
    """Rays from a sphere of `radius` towards random points in a cube of half-side `spread`."""
    rng = np.random.default_rng(seed)
    o = rng.normal(size=(n, 3))
    o = radius * o / np.linalg.norm(o, axis=1, keepdims=True)
    d = rng.uniform(-spread, spread, (n, 3)) - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return o.astype(np.float32), d.astype(np.float32)


@pytest.mark.parametrize("backend", BACKENDS)
def test_single_triangle_hits_and_misses(backend):
    rc = MeshRaycaster(_triangle(), backend=backend)
    o = np.array(
        [[0.2, 0.3, 0.0], [0.2, 0.3, 3.0], [5.0, 5.0, 0.0], [0.2, 0.3, 2.0], [0.1, 0.1, 0]]
    )
    d = np.array([[0, 0, 1.0], [0, 0, -1.0], [0, 0, 1.0], [0, 0, 1.0], [0, 0, 2.0]])
    hits = rc.cast(o, d)
    assert hits.hit.tolist() == [True, True, False, False, True]
    np.testing.assert_allclose(hits.t, [1.0, 2.0, np.inf, np.inf, 0.5], rtol=1e-6)
    assert hits.triangle.tolist() == [0, 0, -1, -1, 0]
    # barycentrics at (0.2, 0.3): weights 0.5, 0.2, 0.3 of v0, v1, v2
    np.testing.assert_allclose(hits.barycentrics[0], [0.5, 0.2, 0.3], atol=1e-6)
    np.testing.assert_allclose(hits.barycentrics[4], [0.8, 0.1, 0.1], atol=1e-6)
    # geometric normal by winding, the same whichever side the ray comes from; 0 on a miss
    np.testing.assert_allclose(hits.normal[:2], [[0, 0, 1.0], [0, 0, 1.0]])
    np.testing.assert_array_equal(hits.normal[2:4], 0.0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_unit_cube_faces_normals_and_update_vertices(backend):
    v, f = _unit_cube()
    rc = MeshRaycaster((v, f), backend=backend)
    o = np.array([[-1.0, 0.3, 0.6], [0.7, 0.7, 3.0], [2.0, 2.0, 2.0]])
    d = np.array([[1.0, 0, 0], [0, 0, -1.0], [1.0, 0, 0]])
    hits = rc.cast(o, d)
    np.testing.assert_allclose(hits.t, [1.0, 2.0, np.inf], rtol=1e-6)
    np.testing.assert_allclose(hits.normal[:2], [[-1.0, 0, 0], [0, 0, 1.0]], atol=1e-6)
    # the hit triangles lie on the faces x = 0 and z = 1
    assert np.all(v[f[hits.triangle[0]], 0] == 0.0)
    assert np.all(v[f[hits.triangle[1]], 2] == 1.0)
    points = o[:2] + hits.t[:2, None] * d[:2]
    corners = v[f[hits.triangle[:2]]]  # [2, 3, 3]
    np.testing.assert_allclose(
        np.einsum("nk,nkd->nd", hits.barycentrics[:2], corners), points, atol=1e-6
    )

    rc.update_vertices(v + [0.5, 0.0, -0.25])  # same triangles, moved
    moved = rc.cast(o, d)
    np.testing.assert_allclose(moved.t, [1.5, 2.25, np.inf], rtol=1e-6)
    assert moved.triangle[0] == hits.triangle[0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_torch_rays_give_tensors_and_empty_inputs(backend):
    rc = MeshRaycaster(trimesh.creation.box(extents=(1.0, 1.0, 1.0)), backend=backend)
    o = torch.tensor([[0.0, 0.0, -2.0], [3.0, 3.0, -2.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    hits = rc.cast(o, d)
    assert isinstance(hits.t, torch.Tensor) and hits.hit.tolist() == [True, False]
    torch.testing.assert_close(hits.t[0], torch.tensor(1.5))
    assert rc.cast(np.zeros((0, 3)), np.zeros((0, 3))).t.shape == (0,)
    empty = MeshRaycaster((np.zeros((0, 3)), np.zeros((0, 3))), backend=backend)
    assert empty.cast(o, d).hit.tolist() == [False, False]
    assert empty.cast_all(o, d, 3).count.tolist() == [0, 0]


@pytest.mark.parametrize("backend", BACKENDS)
def test_camera_depth_of_a_plane(backend):
    plane = (np.array([[-5.0, -5, 0], [5, -5, 0], [5, 5, 0], [-5, 5, 0]]), [[0, 1, 2], [0, 2, 3]])
    cam = Camera(8, 6, 8.0, 8.0, 4.0, 3.0, camera_to_world=look_at([0, 0, 2.0], [0, 0, 0]))
    rc = MeshRaycaster(plane, backend=backend)
    hits = rc.cast_camera(cam)
    assert hits.t.shape == (48,) and hits.hit.all()
    np.testing.assert_allclose(rc.depth(cam), np.full((6, 8), 2.0), rtol=1e-6)
    # the corner pixel (0.5, 0.5) looks 3.5 / 8 and 2.5 / 8 off axis: t = 2 * |(3.5, 2.5, 8)| / 8
    np.testing.assert_allclose(hits.t[0], 2 * np.linalg.norm([3.5, 2.5, 8.0]) / 8, rtol=1e-6)
    assert rc.silhouette(cam).shape == (6, 8) and rc.silhouette(cam).all()
    # a square of side 0.5 at distance 2 spans 0.5 * 8 / 2 = 2 pixels around the centre (4, 3)
    small = MeshRaycaster((plane[0] * 0.05, plane[1]), backend=backend).silhouette(cam)
    assert small.sum() == 4 and small[2:4, 3:5].all()


@pytest.mark.parametrize("backend", BACKENDS)
def test_multiple_hits_in_order(backend):
    inner = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    outer = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
    both = trimesh.util.concatenate([inner, outer])
    rc = MeshRaycaster(both, backend=backend)
    o = np.array([[0.0, 0.0, -3.0], [0.0, 0.8, -3.0], [0.0, 3.0, -3.0]])
    d = np.array([[0.0, 0.0, 1.0]] * 3)
    hits = rc.cast_all(o, d, max_hits=6)
    assert hits.count.tolist() == [4, 2, 0]
    # through the centre: both spheres in and out; the poles are vertices, so exact
    np.testing.assert_allclose(hits.t[0, :4], [2.0, 2.5, 3.5, 4.0], rtol=1e-5)
    assert np.all(hits.triangle[0, :4] >= 0) and np.all(hits.triangle[0, 4:] == -1)
    assert np.all(hits.triangle[0, [1, 2]] < len(inner.faces))  # inner sphere in the middle
    assert np.isinf(hits.t[2]).all()
    # first hit = cast(); truncated to max_hits
    np.testing.assert_allclose(hits.t[:, 0], rc.cast(o, d).t, rtol=1e-6)
    two = rc.cast_all(o, d, max_hits=2)
    np.testing.assert_allclose(two.t, hits.t[:, :2], rtol=1e-6)


def _real_mesh():
    if SPOT.is_file():
        return mesh_arrays(trimesh.load(str(SPOT), process=False, force="mesh"))
    return mesh_arrays(trimesh.creation.icosphere(subdivisions=5, radius=0.6))


def test_open3d_and_embree_agree_on_a_real_mesh():
    v, f = _real_mesh()
    v = 0.6 * (v - v.mean(0)) / np.abs(v - v.mean(0)).max()  # about the size of the rays' target
    o, d = _random_rays(20000)
    a = MeshRaycaster((v, f), backend="open3d")
    b = MeshRaycaster((v, f), backend="embree")
    ha, hb = a.cast(o, d), b.cast(o, d)
    assert 0.2 < ha.hit.mean() < 0.95  # a meaningful mix of hits and misses
    np.testing.assert_array_equal(ha.hit, hb.hit)
    assert (ha.triangle == hb.triangle).mean() > 0.999
    np.testing.assert_allclose(ha.t[ha.hit], hb.t[hb.hit], atol=1e-5)
    same = ha.triangle == hb.triangle
    np.testing.assert_allclose(ha.uv[same], hb.uv[same], atol=1e-4)
    np.testing.assert_array_equal(ha.normal[same], hb.normal[same])

    ma, mb = a.cast_all(o, d, max_hits=6), b.cast_all(o, d, max_hits=6)
    assert (ma.count == mb.count).mean() > 0.999
    assert ma.count.max() >= 4  # the ears and legs: rays cross the mesh more than once
    both = np.isfinite(ma.t) & np.isfinite(mb.t)
    assert (ma.triangle[both] == mb.triangle[both]).mean() > 0.999
    close = np.abs(ma.t[both] - mb.t[both]) < 1e-4
    assert close.mean() > 0.999
    for hits in (ma, mb):  # nearest first, inf padding after the last hit
        later = np.isfinite(hits.t[:, 1:])
        assert np.all(hits.t[:, 1:][later] > hits.t[:, :-1][later])
        assert np.all((hits.triangle >= 0) == np.isfinite(hits.t))


@pytest.mark.parametrize("backend", BACKENDS)
def test_cast_camera_casts_the_mesh_window_only(backend):
    """`cast_camera` casts the pixels of the mesh's `pixel_window` and gives the hits of
    casting every pixel; a mesh out of view has an empty window and no hit."""
    v, f = _unit_cube()
    cam = Camera(
        32, 24, 30.0, 30.0, 16.0, 12.0, camera_to_world=look_at([2.0, -4.0, 1.0], [0, 0, 0])
    )
    rc = MeshRaycaster((v, f), backend=backend)
    row0, row1, col0, col1 = cam.pixel_window(rc.vertices)
    assert 0 < (row1 - row0) * (col1 - col0) < 32 * 24
    every = rc.cast(*cam.rays())
    window = rc.cast_camera(cam)
    assert every.hit.sum() > 10
    for name in ("t", "triangle", "uv", "normal"):
        np.testing.assert_array_equal(getattr(window, name), getattr(every, name))
    right = cam.camera_to_world[:3, 0]  # 6 units to the right at depth ~4.6: u > 50
    away = MeshRaycaster((v + 6.0 * right, f), backend=backend)
    row0, row1, col0, col1 = cam.pixel_window(away.vertices)
    assert (row1 - row0) * (col1 - col0) == 0 and not away.silhouette(cam).any()
