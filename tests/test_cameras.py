"""render/cameras.py: every converter round-trips, and a known 3D point lands on the same pixel
through every representation (projected by hand with K[R|t])."""

from __future__ import annotations

import json

import numpy as np
import pytest

from render import cameras as C
from render.errors import SineError

POINT = np.array([0.1, 0.2, -0.1])  # a world point in front of every test camera


def hand_project(K, R, t, X) -> np.ndarray:
    """x ~ K (R X + t), dehomogenised by hand."""
    x = K @ (R @ X + t)
    return x[:2] / x[2]


def make_cameras() -> list[C.Camera]:
    eyes = [[0.3, -2.0, 0.7], [2.1, 0.4, -0.5], [-1.2, 1.5, 1.9]]
    out = []
    for i, eye in enumerate(eyes):
        c2w = C.look_at(eye, [0.05, 0.1, 0.0])
        out.append(
            C.Camera(
                64 + 8 * i,
                48 + 4 * i,
                70.0 + i,
                72.5 - i,
                31.0 + 0.3 * i,
                25.5 - 0.2 * i,
                camera_to_world=c2w,
                name=f"view{i}.png",
            )
        )
    return out


def expected_pixel(cam: C.Camera) -> np.ndarray:
    w2c = C.invert_pose(cam.camera_to_world)
    return hand_project(cam.K, w2c[:3, :3], w2c[:3, 3], POINT)


def assert_same_camera(a: C.Camera, b: C.Camera, atol=1e-9):
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], atol=atol)
    np.testing.assert_allclose(a.camera_to_world, b.camera_to_world, atol=atol)
    uv_a, _ = a.project(POINT)
    uv_b, _ = b.project(POINT)
    np.testing.assert_allclose(uv_b[0], expected_pixel(a), atol=1e-6)
    np.testing.assert_allclose(uv_a[0], expected_pixel(a), atol=1e-6)


# ---- basics ---------------------------------------------------------------------------------
def test_project_matches_hand_computation():
    # camera at the origin looking down +z: pixel = (fx X/Z + cx, fy Y/Z + cy)
    cam = C.Camera(100, 80, 50.0, 60.0, 50.0, 40.0)
    uv, z = cam.project(np.array([[0.2, -0.1, 2.0]]))
    np.testing.assert_allclose(uv[0], [50 * 0.1 + 50, 60 * -0.05 + 40])
    assert z[0] == pytest.approx(2.0)
    for cam in make_cameras():
        uv, z = cam.project(POINT)
        assert z[0] > 0
        np.testing.assert_allclose(uv[0], expected_pixel(cam), atol=1e-9)
        P = cam.projection
        x = P @ np.append(POINT, 1.0)
        np.testing.assert_allclose(x[:2] / x[2], expected_pixel(cam), atol=1e-9)


def test_pixels_of_points_on_full_and_half_size_images():
    # the camera of the test above: (0.2, -0.1, 2) lands at (55.0, 37.0) -> row 37, col 55
    cam = C.Camera(100, 80, 50.0, 60.0, 50.0, 40.0)
    points = np.array(
        [
            [0.2, -0.1, 2.0],  # inside
            [0.0, 0.0, -1.0],  # behind the camera
            [4.0, 0.0, 2.0],  # u = 150: right of the image
            [0.0, 0.0, 0.0],  # in the camera plane: no pixel at all
            [-2.0, -1.6, 1.0],  # (u, v) = (-50, -56): left of and above the image
        ]
    )
    row, col, inside, z = cam.pixels_of(points)
    np.testing.assert_array_equal(inside, [True, False, False, False, False])
    np.testing.assert_array_equal(row, [37, 0, 0, 0, 0])  # 0 where outside: safe indices
    np.testing.assert_array_equal(col, [55, 0, 0, 0, 0])
    np.testing.assert_allclose(z, [2.0, -1.0, 2.0, 0.0, 1.0])
    row, col, inside, _ = cam.pixels_of(points[:1], shape=(40, 50))  # a half-size mask
    assert (row[0], col[0], inside[0]) == (18, 27, True)


def test_look_at_axes():
    eye, target = np.array([0.0, -3.0, 0.0]), np.zeros(3)
    c2w = C.look_at(eye, target, up=(0, 0, 1))
    R = c2w[:3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], [0, 1, 0], atol=1e-12)  # z forward: towards the target
    np.testing.assert_allclose(R[:, 0], [1, 0, 0], atol=1e-12)  # x right
    np.testing.assert_allclose(R[:, 1], [0, 0, -1], atol=1e-12)  # y down = -up
    np.testing.assert_allclose(c2w[:3, 3], eye)
    # the target projects to the principal point; a point above it projects above (smaller v)
    cam = C.Camera(100, 80, 50.0, 50.0, 50.0, 40.0, camera_to_world=c2w)
    uv, _ = cam.project(np.array([[0, 0, 0], [0, 0, 0.5]]))
    np.testing.assert_allclose(uv[0], [50, 40], atol=1e-9)
    assert uv[1, 1] < 40 and uv[1, 0] == pytest.approx(50)
    # looking straight down the up axis still gives a proper rotation
    R2 = C.look_at([0, 0, 2], [0, 0, 0])[:3, :3]
    np.testing.assert_allclose(R2.T @ R2, np.eye(3), atol=1e-12)
    np.testing.assert_allclose(R2[:, 2], [0, 0, -1], atol=1e-12)


def test_quaternion_round_trip():
    rng = np.random.default_rng(0)
    for _ in range(50):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        q = q if q[0] >= 0 else -q
        R = C.quaternion_to_rotation(q)
        np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(C.rotation_to_quaternion(R), q, atol=1e-9)
    # the branches where the trace is negative (180 degree rotations about each axis)
    for axis in range(3):
        R = -np.eye(3)
        R[axis, axis] = 1.0
        np.testing.assert_allclose(
            C.quaternion_to_rotation(C.rotation_to_quaternion(R)), R, atol=1e-12
        )
    # 90 degrees about z: q = (cos 45, 0, 0, sin 45)
    Rz = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    np.testing.assert_allclose(C.rotation_to_quaternion(Rz), [np.sqrt(0.5), 0, 0, np.sqrt(0.5)])


def test_invert_pose_and_pose_from_rt():
    cam = make_cameras()[0]
    np.testing.assert_allclose(cam.world_to_camera @ cam.camera_to_world, np.eye(4), atol=1e-12)
    w2c = cam.world_to_camera
    np.testing.assert_allclose(
        C.pose_from_rt(w2c[:3, :3], w2c[:3, 3]), cam.camera_to_world, atol=1e-12
    )


def test_resized_scales_intrinsics_exactly():
    cam = C.Camera(640, 480, 1520.4, 1525.9, 302.32, 246.87)
    small = cam.resized(320, 240)
    assert (small.width, small.height) == (320, 240)
    np.testing.assert_allclose(
        [small.fx, small.fy, small.cx, small.cy], [760.2, 762.95, 151.16, 123.435]
    )
    # the image centre maps to the image centre, a pixel's corner to the scaled corner
    cam = make_cameras()[1]
    half = cam.resized(cam.width // 2, cam.height // 2)
    uv, _ = cam.project(POINT)
    uv2, _ = half.project(POINT)
    np.testing.assert_allclose(uv2, uv / 2, atol=1e-9)
    np.testing.assert_allclose(half.camera_to_world, cam.camera_to_world)


def test_rays_pass_through_projected_point():
    for cam in make_cameras():
        uv, z = cam.project(POINT)
        origins, dirs = cam.rays(uv)
        assert origins.dtype == np.float32 and dirs.dtype == np.float32
        np.testing.assert_allclose(np.linalg.norm(dirs, axis=1), 1.0, atol=1e-6)
        np.testing.assert_allclose(origins[0], cam.center, atol=1e-6)
        to_point = POINT - cam.center
        dist = np.linalg.norm(to_point)
        np.testing.assert_allclose(origins[0] + dist * dirs[0], POINT, atol=1e-5)
        # depth = t * z_per_unit_distance
        zpu = cam.z_per_unit_distance(uv)
        assert dist * zpu[0] == pytest.approx(z[0], rel=1e-6)
    cam = C.Camera(4, 3, 2.0, 2.0, 2.0, 1.5)
    _, dirs = cam.rays()
    assert dirs.shape == (12, 3)
    # first pixel centre (0.5, 0.5): direction ~ ((0.5-2)/2, (0.5-1.5)/2, 1)
    d = np.array([-0.75, -0.5, 1.0])
    np.testing.assert_allclose(dirs[0], d / np.linalg.norm(d), atol=1e-6)
    np.testing.assert_allclose(cam.pixel_grid()[:2], [[0.5, 0.5], [1.5, 0.5]])


# ---- transforms.json ------------------------------------------------------------------------
def test_transforms_round_trip():
    cams = make_cameras()
    cams[0] = cams[0].replace(distortion=np.array([0.01, -0.002, 0.001, 0.0005]))
    cams[1] = cams[1].replace(distortion=np.array([0.01, -0.002, 0.001, 0.0005, 0.003]))
    paths = [f"images/{c.name}" for c in cams]
    data = json.loads(json.dumps(C.cameras_to_transforms(cams, paths)))  # through real JSON
    # OpenGL axes in the file: the camera looks along -z of its transform
    c2w_gl = np.array(data["frames"][0]["transform_matrix"])
    forward = cams[0].camera_to_world[:3, 2]
    np.testing.assert_allclose(-c2w_gl[:3, 2], forward, atol=1e-12)
    back = C.cameras_from_transforms(data)
    assert [p for p, _ in back] == paths
    for cam, (_, got) in zip(cams, back, strict=True):
        assert_same_camera(cam, got)
        assert got.name == cam.name
    np.testing.assert_allclose(back[0][1].distortion, [0.01, -0.002, 0.001, 0.0005])
    np.testing.assert_allclose(back[1][1].distortion, [0.01, -0.002, 0.001, 0.0005, 0.003])
    assert not back[2][1].distortion.any()


def test_transforms_nerf_camera_angle_x():
    cam = C.Camera(80, 60, 0.0, 0.0, 40.0, 30.0, camera_to_world=make_cameras()[2].camera_to_world)
    angle = 0.6911112070083618  # the NeRF synthetic scenes' field of view
    f = 0.5 * 80 / np.tan(0.5 * angle)
    cam = cam.replace(fx=f, fy=f)
    data = {
        "camera_angle_x": angle,
        "frames": [
            {
                "file_path": "./train/r_0",
                "transform_matrix": (cam.camera_to_world @ C.OPENCV_TO_OPENGL).tolist(),
            }
        ],
    }
    with pytest.raises(SineError, match="image size"):
        C.cameras_from_transforms(data)
    ((path, got),) = C.cameras_from_transforms(data, image_sizes={"./train/r_0": (80, 60)})
    assert path == "./train/r_0"
    assert got.name == "r_0"
    assert_same_camera(cam, got)
    with pytest.raises(SineError, match="focal"):
        C.cameras_from_transforms({"w": 8, "h": 6, "frames": data["frames"]})
    with pytest.raises(SineError, match="no frames"):
        C.cameras_from_transforms({"frames": []})


# ---- COLMAP ---------------------------------------------------------------------------------
def test_colmap_text_round_trip_through_pycolmap(tmp_path):
    cams = make_cameras()
    cams[1] = cams[1].replace(distortion=np.array([0.02, -0.01, 0.001, -0.002]))
    cams[2] = cams[2].replace(distortion=np.array([0.02, -0.01, 0.001, -0.002, 0.1, 0, 0, 0.01]))
    C.write_colmap_text(tmp_path, cams)
    models = [line.split()[1] for line in (tmp_path / "cameras.txt").read_text().splitlines()]
    assert models == ["OPENCV", "OPENCV", "FULL_OPENCV"]
    back = C.read_colmap_model(tmp_path)
    assert [n for n, _ in back] == [c.name for c in cams]
    for cam, (_, got) in zip(cams, back, strict=True):
        assert_same_camera(cam, got)
        np.testing.assert_allclose(
            got.distortion[: len(cam.distortion)], cam.distortion, atol=1e-12
        )
    # the COLMAP pose helpers are each other's inverse
    q, t = C.c2w_to_colmap_pose(cams[2].camera_to_world)
    np.testing.assert_allclose(C.colmap_pose_to_c2w(q, t), cams[2].camera_to_world, atol=1e-12)
    R = C.quaternion_to_rotation(q)
    np.testing.assert_allclose(hand_project(cams[2].K, R, t, POINT), expected_pixel(cams[2]))


def test_colmap_intrinsics_models():
    cam = C.camera_from_colmap_intrinsics("SIMPLE_RADIAL", [100, 50, 40, 0.1], 100, 80)
    assert (cam.fx, cam.fy, cam.cx, cam.cy) == (100, 100, 50, 40)
    np.testing.assert_allclose(cam.distortion, [0.1, 0, 0, 0])
    cam = C.camera_from_colmap_intrinsics("RADIAL", [100, 50, 40, 0.1, 0.2], 100, 80)
    np.testing.assert_allclose(cam.distortion, [0.1, 0.2, 0, 0])
    cam = C.camera_from_colmap_intrinsics("PINHOLE", [100, 90, 50, 40], 100, 80)
    assert (cam.fx, cam.fy) == (100, 90) and not cam.distortion.any()
    full = [100, 90, 50, 40, 0.1, 0.2, 0.01, 0.02, 0.3, 0.01, 0.02, 0.03]
    cam = C.camera_from_colmap_intrinsics("FULL_OPENCV", full, 100, 80)
    np.testing.assert_allclose(cam.distortion, full[4:])  # OpenCV's 8-coefficient order
    with pytest.raises(SineError, match="not supported"):
        C.camera_from_colmap_intrinsics("OPENCV_FISHEYE", [1, 1, 1, 1, 0, 0, 0, 0], 10, 10)


def test_read_colmap_model_errors(tmp_path):
    with pytest.raises(SineError, match="COLMAP"):
        C.read_colmap_model(tmp_path / "nothing")


# ---- Middlebury -----------------------------------------------------------------------------
def test_middlebury_par_round_trip(tmp_path):
    cams = make_cameras()
    path = tmp_path / "x_par.txt"
    C.write_middlebury_par(path, cams)
    assert path.read_text().splitlines()[0] == "3"
    rows = C.read_middlebury_par(path)
    assert [r[0] for r in rows] == [c.name for c in cams]
    for cam, (name, K, R, t) in zip(cams, rows, strict=True):
        np.testing.assert_allclose(hand_project(K, R, t, POINT), expected_pixel(cam), atol=1e-9)
        got = C.camera_from_krt(K, R, t, cam.width, cam.height, name)
        assert_same_camera(cam, got)
    bad = tmp_path / "bad_par.txt"
    bad.write_text("1\nimg.png 1 2 3\n")
    with pytest.raises(SineError, match="expected"):
        C.read_middlebury_par(bad)


def test_middlebury_real_par_file():
    par = _data() / "middlebury-templeSparseRing" / "templeSR_par.txt"
    if not par.is_file():
        pytest.skip("shared data missing")
    rows = C.read_middlebury_par(par)
    assert len(rows) == 16
    name, K, R, t = rows[0]
    assert name == "templeSR0001.png"
    assert K[0, 0] == pytest.approx(1520.4) and K[1, 2] == pytest.approx(246.87)
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-6)


# ---- NeuS / IDR -----------------------------------------------------------------------------
def test_neus_round_trip(tmp_path):
    cams = make_cameras()
    scale_mat = np.diag([0.5, 0.5, 0.5, 1.0])
    scale_mat[:3, 3] = [0.1, -0.2, 0.3]
    data = C.cameras_to_neus(cams, scale_mat)
    np.savez(tmp_path / "cameras_sphere.npz", **data)
    with np.load(tmp_path / "cameras_sphere.npz") as npz:
        # the NeuS convention: world_mat is K[R|t] (4x4) and projects world points directly
        x = npz["world_mat_1"] @ np.append(POINT, 1.0)
        np.testing.assert_allclose(x[:2] / x[2], expected_pixel(cams[1]), atol=1e-9)
        back, got_scale = C.cameras_from_neus(npz, [(c.width, c.height) for c in cams])
    np.testing.assert_allclose(got_scale, scale_mat)
    for cam, got in zip(cams, back, strict=True):
        assert_same_camera(cam, got, atol=1e-7)
    with pytest.raises(SineError, match="world_mat_3"):
        C.cameras_from_neus(data, [(64, 48)] * 4)


# ---- 3x4 projection matrices ----------------------------------------------------------------
@pytest.mark.parametrize("scale", [1.0, 3.7, -1.0, -0.02])
def test_decompose_projection(scale):
    for cam in make_cameras():
        P = scale * cam.projection
        K, R, t = C.decompose_projection(P)
        np.testing.assert_allclose(K, cam.K, atol=1e-8)
        np.testing.assert_allclose(R, cam.world_to_camera[:3, :3], atol=1e-9)
        np.testing.assert_allclose(t, cam.world_to_camera[:3, 3], atol=1e-9)
        assert np.linalg.det(R) == pytest.approx(1.0)
        np.testing.assert_allclose(hand_project(K, R, t, POINT), expected_pixel(cam), atol=1e-7)
        got = C.camera_from_projection(P, cam.width, cam.height, cam.name)
        assert_same_camera(cam, got, atol=1e-8)
        assert got.project(POINT)[1][0] > 0  # the point stays in front of the camera


def test_decompose_projection_with_flipped_axes():
    # a camera whose K has negative focal lengths in the raw RQ output: still a proper result
    cam = make_cameras()[0]
    M = cam.projection
    for sign in ([-1, 1, 1], [1, -1, 1], [-1, -1, 1]):
        # the same projection, written with signs moved between K and R: P is unchanged
        S = np.diag(sign)
        K = cam.K @ S
        R = S @ cam.world_to_camera[:3, :3]
        P = K @ np.hstack([R, (S @ cam.world_to_camera[:3, 3])[:, None]])
        np.testing.assert_allclose(P, M, atol=1e-9)
        K2, R2, _ = C.decompose_projection(P)
        assert (np.diag(K2) > 0).all()
        np.testing.assert_allclose(K2, cam.K, atol=1e-8)


# ---- cameras.json ---------------------------------------------------------------------------
def test_camera_set_round_trip(tmp_path):
    cams = make_cameras()
    cams[2] = cams[2].replace(split="test")
    cs = C.CameraSet(cams, scale=0.37, center=np.array([0.1, -0.2, 0.5]), extra={"source": "x"})
    C.save_cameras(tmp_path / "cameras.json", cs)
    d = json.loads((tmp_path / "cameras.json").read_text())
    assert d["convention"] == "opencv" and d["normalization"]["scale"] == 0.37
    assert d["source"] == "x"
    back = C.load_cameras(tmp_path / "cameras.json")
    assert back.scale == pytest.approx(0.37) and back.extra == {"source": "x"}
    for cam, got in zip(cams, back.frames, strict=True):
        assert_same_camera(cam, got)
        assert (got.name, got.split) == (cam.name, cam.split)
    assert [c.name for c in back.split("test")] == ["view2.png"]
    assert set(back.by_name()) == {"view0.png", "view1.png", "view2.png"}
    with pytest.raises(SineError, match="opencv"):
        C.CameraSet.from_dict({"convention": "opengl", "frames": []})


def _data():
    from pathlib import Path

    return Path(__file__).resolve().parents[1].parent / "shared" / "data"
