"""recon stages on tiny hand-made data: masks, normalisation, TSDF proxy mesh, error paths."""

from __future__ import annotations

import numpy as np
import pytest
from scene_helpers import ring, sphere_depths, sphere_masks

from recon.masks import compute_masks, segment_foreground
from recon.normalize import apply_normalization, compute_normalization, up_axis
from recon.poses import SfmParams, prepare_sfm_images, run_sfm
from recon.proxy_mesh import clean_mesh, fuse_tsdf, mesh_stats
from render.cameras import CameraSet
from render.errors import SineError
from render.io import write_image, write_mask


def keyed_scene(h: int = 120, w: int = 160, seed: int = 0):
    """An orange shaded ellipse with a dark notch on a noisy blue backdrop + a grey top band."""
    rng = np.random.default_rng(seed)
    img = np.zeros((h, w, 3), np.float32) + np.array([0.25, 0.3, 0.75], np.float32)
    img[: h // 6] = (0.45, 0.45, 0.5)  # a grey wall strip, also backdrop
    img += rng.normal(0, 0.02, img.shape).astype(np.float32)
    v, u = np.mgrid[0:h, 0:w]
    gt = ((u - 80) / 35.0) ** 2 + ((v - 65) / 45.0) ** 2 <= 1
    shade = 0.6 + 0.4 * (1 - (u - 80) / 70.0)
    img[gt] = np.stack([0.9 * shade, 0.5 * shade, 0.15 * shade], -1)[gt]
    return np.clip(img, 0, 1), gt


def test_mask_on_keyed_backdrop():
    img, gt = keyed_scene()
    mask = segment_foreground(img)
    iou = (mask & gt).sum() / (mask | gt).sum()
    assert iou > 0.95


def test_empty_mask_is_a_clear_error(tmp_path):
    img = np.zeros((60, 80, 3), np.float32) + np.array([0.2, 0.3, 0.8], np.float32)
    write_image(tmp_path / "a.png", img)
    with pytest.raises(SineError, match="empty foreground mask"):
        compute_masks([tmp_path / "a.png"], [tmp_path / "m" / "a.png"])


def given_mask_wins(tmp_path):
    img, gt = keyed_scene()
    write_image(tmp_path / "a.png", img)
    user = np.zeros_like(gt)
    user[10:20, 10:20] = True
    write_mask(tmp_path / "a_mask.png", user)
    out = compute_masks([tmp_path / "a.png"], [tmp_path / "a_mask.png"])
    assert out["auto"] == [] and out["coverage"]["a.png"] == pytest.approx(user.mean())


def test_given_mask_wins(tmp_path):
    given_mask_wins(tmp_path)


def test_normalisation_of_a_known_ring():
    center, r = np.array([1.0, 2.0, 3.0]), 0.5
    cams, axis = ring(center=center)
    assert up_axis(cams) == pytest.approx(axis, abs=1e-6)  # cameras look down -> +axis
    norm, _ = compute_normalization(cams, sphere_masks(cams, center, r), target_radius=0.8)
    # The hull of a sphere seen from one ring is the sphere plus caps along the axis (cone
    # intersections), so the centre is exact across the axis and close along it, and the
    # bounding radius >= r (scale * r <= 0.8).
    c = norm.apply_points(center[None])[0]
    assert np.linalg.norm(c[:2]) < 0.01 and abs(c[2]) < 0.06
    assert 0.65 < norm.scale * r <= 0.8 + 1e-3
    assert norm.rotation @ axis == pytest.approx([0, 0, 1], abs=1e-6)
    new = apply_normalization(CameraSet(frames=cams), norm)
    assert new.frames[0].center[:2] @ [1, 0] == pytest.approx(0, abs=1e-6)  # first camera on -y
    assert new.frames[0].center[1] < 0
    # stored normalisation maps input points: x_run = scale * R (x - center)
    x = np.array([[1.3, 1.7, 3.2]])
    assert new.scale * (x - new.center) @ new.rotation.T == pytest.approx(norm.apply_points(x))


def test_tsdf_proxy_from_gt_depth_is_the_sphere_and_arap_runs():
    import open3d as o3d

    center, r = np.zeros(3), 0.6
    cams, _ = ring(n=10, center=center, axis=(0, 0, 1), radius=2.5, height=1.0)
    cams += ring(n=6, center=center, axis=(0, 0, 1), radius=2.0, height=-1.8)[0]
    depths = sphere_depths(cams, center, r)
    mesh = clean_mesh(fuse_tsdf(cams, depths, voxel_size=1 / 64), target_triangles=5000)
    radii = np.linalg.norm(np.asarray(mesh.vertices), axis=1)
    assert np.abs(radii - r).max() < 2 / 64
    stats = mesh_stats(mesh)
    assert stats["proxy_triangles"] <= 5000 and stats["proxy_volume"] > 0  # outward normals
    assert stats["proxy_edge_manifold"]
    handles = [0, len(mesh.vertices) // 2]
    positions = np.asarray(mesh.vertices)[handles] + [0.05, 0, 0]
    moved = mesh.deform_as_rigid_as_possible(
        o3d.utility.IntVector(handles), o3d.utility.Vector3dVector(positions), max_iter=5
    )
    assert len(moved.vertices) == len(mesh.vertices)
    assert np.isfinite(np.asarray(moved.vertices)).all()


def test_too_few_registered_views_is_an_error(tmp_path):
    rng = np.random.default_rng(0)
    views = []
    for i in range(4):
        write_image(tmp_path / f"n{i}.png", rng.random((96, 128, 3)).astype(np.float32))
        write_mask(tmp_path / f"n{i}_m.png", np.ones((96, 128), bool))
        views.append((f"n{i}.png", tmp_path / f"n{i}.png", tmp_path / f"n{i}_m.png", None))
    images, masks = prepare_sfm_images(views, tmp_path / "sfm", 1600)
    with pytest.raises(SineError, match="registered .* of 4 views|registered no views"):
        run_sfm(images, masks, [v[0] for v in views], tmp_path / "sfm", SfmParams())


def test_mixed_image_sizes_are_an_error_for_sfm(tmp_path):
    views = []
    for i, (w, h) in enumerate([(128, 96), (100, 96)]):
        write_image(tmp_path / f"n{i}.png", np.zeros((h, w, 3), np.float32))
        write_mask(tmp_path / f"n{i}_m.png", np.ones((h, w), bool))
        views.append((f"n{i}.png", tmp_path / f"n{i}.png", tmp_path / f"n{i}_m.png", None))
    with pytest.raises(SineError, match="different sizes"):
        prepare_sfm_images(views, tmp_path / "sfm", 1600)


def test_canonical_order_is_the_same_for_any_order_of_the_same_mesh():
    import open3d as o3d

    from recon.proxy_mesh import canonical_order, signed_volume

    box = o3d.geometry.TriangleMesh.create_box()
    rng = np.random.default_rng(0)
    perm = rng.permutation(len(box.vertices))  # new vertex i is old vertex perm[i]
    shuffled = o3d.geometry.TriangleMesh()
    shuffled.vertices = o3d.utility.Vector3dVector(np.asarray(box.vertices)[perm])
    inverse = np.argsort(perm)
    tris = inverse[np.asarray(box.triangles)][rng.permutation(len(box.triangles))]
    shuffled.triangles = o3d.utility.Vector3iVector(np.roll(tris, 1, axis=1).astype(np.int32))
    a, b = canonical_order(box), canonical_order(shuffled)
    assert np.array_equal(np.asarray(a.vertices), np.asarray(b.vertices))
    assert np.array_equal(np.asarray(a.triangles), np.asarray(b.triangles))
    assert np.all(np.diff(np.asarray(a.vertices)[:, 0]) >= 0)  # sorted by x first
    assert signed_volume(a) == pytest.approx(signed_volume(box))  # the winding kept: volume 1
