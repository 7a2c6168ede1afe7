"""Outputs people use: camera paths (nerfstudio format), orbits, video, coloured mesh export in
the capture's units, the viewer's headless screenshot, PSNR/SSIM evaluation, `load_scene`."""

import json
import shutil

import numpy as np
import open3d as o3d
import pytest
import trimesh

import sine_cli
from edit.scene import load_scene
from render.camera_paths import (
    camera_path_dict,
    cameras_from_camera_path,
    orbit_cameras,
    read_camera_path,
    write_camera_path,
)
from render.cameras import Camera, CameraSet, load_cameras, look_at
from render.errors import SineError
from render.evaluation import image_metrics, to_run_frame
from render.io import read_image, write_json
from render.mesh_export import denormalize_points, save_colored_mesh, surface_colors
from render.renderer import EDGE_SPREAD
from render.video import video_info, write_video
from render.viewer import build_scene, screen_right, screenshot, view_direction


def _ring(n, elevation_deg, distance, size=(64, 48)):
    cams = []
    for i in range(n):
        a, e = 2 * np.pi * i / n + 0.3, np.radians(elevation_deg)
        eye = distance * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
        cams.append(
            Camera(*size, 70.0, 60.0, 30.0, 25.0, look_at(eye, np.zeros(3)), name=f"c{i}.png")
        )
    return cams


# ---- camera paths -------------------------------------------------------------------------
def test_camera_path_round_trip_nerfstudio_format(tmp_path):
    rng = np.random.default_rng(0)
    cams = []
    for _ in range(5):  # fx != fy, off-centre principal point, arbitrary poses
        eye = rng.normal(size=3) * 3
        cams.append(Camera(80, 60, 71.5, 69.25, 41.2, 28.7, look_at(eye, rng.normal(size=3) * 0.1)))
    path = tmp_path / "camera_path.json"
    write_camera_path(path, cams, fps=10)
    data = json.loads(path.read_text())
    assert data["render_width"] == 80 and data["render_height"] == 60
    assert data["seconds"] == pytest.approx(0.5)
    entry = data["camera_path"][0]
    assert len(entry["camera_to_world"]) == 16
    assert entry["aspect"] == pytest.approx(80 / 60)
    assert entry["fov"] == pytest.approx(np.degrees(2 * np.arctan(30 / 69.25)))
    back = read_camera_path(path)
    for a, b in zip(cams, back, strict=True):
        np.testing.assert_allclose(b.camera_to_world, a.camera_to_world, atol=1e-6)
        np.testing.assert_allclose([b.fx, b.fy, b.cx, b.cy], [a.fx, a.fy, a.cx, a.cy], atol=1e-6)
        assert (b.width, b.height) == (a.width, a.height)


def test_camera_path_reads_plain_nerfstudio_entries():
    """Only nerfstudio's keys: fx = fy = H / 2 / tan(fov / 2), centred principal point, and
    camera_to_world in OpenGL axes (a camera at -3y looking at the origin looks along -z_gl)."""
    c2w_gl = np.eye(4)
    c2w_gl[:3, :3] = [[1, 0, 0], [0, 0, -1], [0, 1, 0]]  # columns: x, y_gl up = +z, z_gl = -y
    c2w_gl[:3, 3] = [0, -3, 0]
    data = {
        "render_width": 100,
        "render_height": 50,
        "camera_path": [{"camera_to_world": c2w_gl.ravel().tolist(), "fov": 90.0, "aspect": 2}],
    }
    (cam,) = cameras_from_camera_path(data)
    assert cam.fx == pytest.approx(25.0) and cam.fy == pytest.approx(25.0)
    assert (cam.cx, cam.cy) == (50.0, 25.0)
    np.testing.assert_allclose(cam.camera_to_world, look_at([0, -3, 0], np.zeros(3)), atol=1e-12)
    assert cam.project(np.zeros((1, 3)))[0][0] == pytest.approx([50.0, 25.0])
    np.testing.assert_allclose(
        camera_path_dict([cam])["camera_path"][0]["camera_to_world"], c2w_gl.ravel(), atol=1e-12
    )
    assert camera_path_dict([cam])["camera_path"][0]["fov"] == pytest.approx(90.0)


def test_orbit_looks_at_origin_at_mean_elevation_and_distance():
    captures = _ring(6, 20.0, 3.0) + _ring(6, 40.0, 5.0)  # mean elevation 30, mean distance 4
    orbit = orbit_cameras(captures, 12, width=32)
    assert len(orbit) == 12
    for cam in orbit:
        c = cam.center
        assert np.linalg.norm(c) == pytest.approx(4.0)
        assert np.degrees(np.arcsin(c[2] / np.linalg.norm(c))) == pytest.approx(30.0)
        np.testing.assert_allclose(c + np.linalg.norm(c) * cam.camera_to_world[:3, 2], 0, atol=1e-9)
        assert cam.camera_to_world[2, 1] < 0  # image down points down: +z is up in the frame
        assert (cam.width, cam.height) == (32, 24)
        assert (cam.fx, cam.fy, cam.cx, cam.cy) == pytest.approx((35.0, 30.0, 15.0, 12.5))
    azimuths = np.unwrap([np.arctan2(c.center[1], c.center[0]) for c in orbit])
    assert azimuths[0] == pytest.approx(0.3)  # starts at the first capture's azimuth
    np.testing.assert_allclose(np.diff(azimuths), 2 * np.pi / 12)


# ---- video --------------------------------------------------------------------------------
def test_video_round_trip_frame_count_and_size(tmp_path):
    frames = [np.full((30, 40, 3), i / 10, np.float32) for i in range(7)]
    write_video(tmp_path / "a.mp4", frames, fps=12)
    assert video_info(tmp_path / "a.mp4") == {"frames": 7, "width": 40, "height": 30, "fps": 12.0}
    write_video(tmp_path / "odd.mp4", [np.zeros((31, 41, 3), np.uint8)] * 3)
    info = video_info(tmp_path / "odd.mp4")  # H.264 yuv420p: padded to even sizes
    assert (info["frames"], info["width"], info["height"]) == (3, 42, 32)
    with pytest.raises(SineError):
        write_video(tmp_path / "none.mp4", [])
    assert not (tmp_path / "none.mp4").exists()


# ---- mesh colours and export --------------------------------------------------------------
def test_surface_colors_see_the_surface_along_the_normal():
    """A sphere of radius 0.5 (density 200 inside) whose colour is the unit-cube position: the
    colour seen at a surface point is the colour just inside it, whatever the view-dependent
    term does away from the surface."""

    def field(x, d):
        inside = (x.norm(dim=1) < 0.5).float()
        rgb = (x * 0.5 + 0.5).clamp(0, 1) + 10.0 * (1 - inside)[:, None]  # wrong outside
        return {"sigma": 200.0 * inside, "rgb": rgb.clamp(0, 1)}

    rng = np.random.default_rng(1)
    n = rng.normal(size=(50, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    colors = surface_colors(field, 0.5 * n, n, band=0.04, samples=16)
    np.testing.assert_allclose(colors, 0.5 * (0.5 * n) + 0.5, atol=0.02)


def test_denormalize_inverts_the_run_normalization():
    rng = np.random.default_rng(2)
    R = np.linalg.qr(rng.normal(size=(3, 3)))[0]
    R *= np.sign(np.linalg.det(R))
    x_in = rng.normal(size=(20, 3))
    scale, center = 0.37, np.array([0.1, -0.2, 0.5])
    x_run = scale * (x_in - center) @ R.T
    np.testing.assert_allclose(denormalize_points(x_run, scale, center, R), x_in, atol=1e-12)


def test_cameras_json_keeps_the_normalization_rotation(tmp_path):
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    from render.cameras import save_cameras

    save_cameras(tmp_path / "cameras.json", CameraSet(_ring(3, 10, 2), scale=2.0, rotation=R))
    np.testing.assert_allclose(load_cameras(tmp_path / "cameras.json").rotation, R)


@pytest.mark.parametrize("suffix", [".ply", ".glb", ".obj"])
def test_colored_mesh_reloads_with_colours(tmp_path, suffix):
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.5, 8)
    v, f = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    colors = np.random.default_rng(3).uniform(size=(len(v), 3))
    save_colored_mesh(tmp_path / f"m{suffix}", v, f, colors)
    tm = trimesh.load(tmp_path / f"m{suffix}", process=False, force="mesh")
    assert len(tm.vertices) == len(v) and len(tm.faces) == len(f)
    np.testing.assert_allclose(tm.vertices, v, atol=1e-6)
    np.testing.assert_allclose(tm.visual.vertex_colors[:, :3] / 255.0, colors, atol=1 / 255)
    om = o3d.io.read_triangle_mesh(str(tmp_path / f"m{suffix}"))
    assert om.has_vertex_colors() and len(om.vertices) == len(v)
    # Open3D's glTF/OBJ readers may reorder vertices: compare by position.
    order = [int(np.argmin(np.linalg.norm(v - p, axis=1))) for p in np.asarray(om.vertices)]
    np.testing.assert_allclose(np.asarray(om.vertex_colors), colors[order], atol=1 / 255)


def test_sine_export_in_capture_units(tiny_fitted_run, tmp_path):
    run = tmp_path / "run"
    shutil.copytree(tiny_fitted_run, run, ignore=shutil.ignore_patterns("edits", "features"))
    cams = json.loads((run / "cameras.json").read_text())
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # 90 degrees about z
    cams["normalization"] = {"scale": 2.0, "center": [1.0, -2.0, 0.5], "rotation": R.tolist()}
    write_json(run / "cameras.json", cams)
    proxy = trimesh.load(run / "proxy_mesh.ply", process=False)
    for suffix in (".ply", ".glb"):
        out = tmp_path / f"mesh{suffix}"
        assert sine_cli.main(["export", str(run), "--out", str(out), "--device", "cpu"]) == 0
        tm = trimesh.load(out, process=False, force="mesh")
        assert len(tm.vertices) == len(proxy.vertices)
        expected = proxy.vertices @ R / 2.0 + [1.0, -2.0, 0.5]  # x_in = R^T x_run / s + c
        np.testing.assert_allclose(tm.vertices, expected, atol=1e-5)
        rgb = tm.visual.vertex_colors[:, :3]
        assert rgb.std(axis=0).max() > 2  # coloured by the field, not one flat colour
    assert (
        sine_cli.main(["export", str(run), "--out", str(tmp_path / "n.ply"), "--normalized"]) == 0
    )
    tm = trimesh.load(tmp_path / "n.ply", process=False)
    np.testing.assert_allclose(tm.vertices, proxy.vertices, atol=1e-6)
    # the field's colours resemble the captures': mean vertex colour vs mean object pixel
    images = [read_image(p) for p in sorted((run / "images").glob("*.png"))]
    masks = [read_image(p)[..., 0] > 0.5 for p in sorted((run / "masks").glob("*.png"))]
    mean_obj = np.mean(np.concatenate([i[m] for i, m in zip(images, masks, strict=True)]), 0)
    assert np.abs(rgb.mean(0) / 255.0 - mean_obj).max() < 0.15


# ---- render, view, eval on a fitted run ---------------------------------------------------
def test_sine_render_writes_frames_camera_path_and_playable_mp4(tiny_fitted_run, tmp_path):
    out = tmp_path / "orbit"
    argv = ["render", str(tiny_fitted_run), "--out", str(out), "--orbit", "5", "--width", "48"]
    argv += ["--video", str(out / "orbit.mp4"), "--depth", "--opacity", "--quiet", "--threads", "1"]
    assert sine_cli.main(argv) == 0
    assert video_info(out / "orbit.mp4")["frames"] == 5
    assert (video_info(out / "orbit.mp4")["width"], video_info(out / "orbit.mp4")["height"]) == (
        48,
        48,
    )
    for sub in ("rgb", "depth", "opacity"):
        assert len(list((out / sub).glob("*.png"))) == 5
    frame = read_image(out / "rgb" / "0000.png")
    assert frame.shape == (48, 48, 3)
    assert (np.abs(frame - 1.0).max(axis=2) > 0.1).mean() > 0.02  # the object is there
    path = read_camera_path(out / "camera_path.json")
    expected = orbit_cameras(load_cameras(tiny_fitted_run / "cameras.json").frames, 5, 48)
    for a, b in zip(path, expected, strict=True):
        np.testing.assert_allclose(a.camera_to_world, b.camera_to_world, atol=1e-6)
    # the written path renders again (--camera-path), the capture views too (--views)
    again = tmp_path / "again"
    argv = ["render", str(tiny_fitted_run), "--out", str(again), "--quiet"]
    assert sine_cli.main(argv + ["--camera-path", str(out / "camera_path.json")]) == 0
    np.testing.assert_allclose(read_image(again / "rgb" / "0000.png"), frame, atol=2 / 255)
    assert sine_cli.main(argv + ["--views", "test", "--width", "32"]) == 0
    assert read_image(again / "rgb" / "r_007.png").shape == (32, 32, 3)


def test_sine_render_refuses_compare_without_an_edit(tiny_fitted_run, tmp_path):
    argv = ["render", str(tiny_fitted_run), "--out", str(tmp_path), "--compare"]
    assert sine_cli.main(argv) == 2


def test_load_scene_template_and_missing_edit(tiny_fitted_run):
    scene = load_scene(tiny_fitted_run, device="cpu")
    assert scene.name == "template"
    v, t = scene.mesh()
    assert v.shape[1] == 3 and t.shape[1] == 3 and t.max() < len(v)
    cam = load_cameras(tiny_fitted_run / "cameras.json").frames[0].resized(16, 16)
    out = scene.render_view(cam)
    assert set(out) == {"rgb", "opacity", "depth", "z"}
    assert out["rgb"].shape == (16, 16, 3) and out["z"].shape == (16, 16)
    # supersample 2 (the fit's default): each pixel is the mean of the 2 x 2 pixels of a
    # twice larger render with one ray per pixel; where those differ in opacity (a silhouette
    # crosses the pixel), of the 4 x 4 pixels of a 4 x larger one
    assert scene.supersample == 2  # the template's `sine fit --supersample`
    smooth = scene.render_view(cam)
    one_ray = load_scene(tiny_fitted_run, device="cpu", supersample=1)
    big, bigger = (one_ray.render_view(cam.resized(16 * s, 16 * s)) for s in (2, 4))
    sub = big["opacity"].reshape(16, 2, 16, 2)
    again = sub.max(axis=(1, 3)) - sub.min(axis=(1, 3)) > EDGE_SPREAD
    assert again.any() and not again.all()
    for key in ("rgb", "opacity"):
        two = big[key].reshape(16, 2, 16, 2, -1).mean(axis=(1, 3)).reshape(smooth[key].shape)
        four = bigger[key].reshape(16, 4, 16, 4, -1).mean(axis=(1, 3)).reshape(smooth[key].shape)
        np.testing.assert_allclose(smooth[key][~again], two[~again], atol=1e-5)
        np.testing.assert_allclose(smooth[key][again], four[again], atol=1e-5)
    with pytest.raises(SineError, match="edit nope not found"):
        load_scene(tiny_fitted_run, edit="nope", device="cpu")


def _regions(image, background=1.0):
    """Connected non-background regions larger than 1% of the image, after removing thin lines
    (frustums) with a 5x5 opening."""
    import cv2

    fg = (np.abs(image - background).max(axis=2) > 0.08).astype(np.uint8)
    fg = cv2.morphologyEx(fg, cv2.MORPH_OPEN, np.ones((5, 5), np.uint8))
    n, labels, stats, _ = cv2.connectedComponentsWithStats(fg)
    return [i for i in range(1, n) if stats[i, cv2.CC_STAT_AREA] > 0.01 * fg.size], labels


def test_viewer_screenshot_shows_both_meshes_headless(tmp_path):
    box = o3d.geometry.TriangleMesh.create_box(0.8, 0.6, 0.5).translate([-0.4, -0.3, -0.25])
    v, f = np.asarray(box.vertices), np.asarray(box.triangles)
    red, blue = np.tile([0.9, 0.1, 0.1], (len(v), 1)), np.tile([0.1, 0.2, 0.9], (len(v), 1))
    cams = _ring(8, 25.0, 2.5)
    scene = build_scene((v, f, red), (v * [1, 1, 1.6], f, blue), cams, highlight=2)
    image = screenshot(scene, tmp_path / "view.png", 480, 270)
    assert image.shape == (270, 480, 3)
    assert read_image(tmp_path / "view.png").shape == (270, 480, 3)
    regions, labels = _regions(image)
    assert len(regions) == 2
    left, right = sorted(regions, key=lambda r: np.nonzero(labels == r)[1].mean())
    gap = np.nonzero(labels == right)[1].mean() - np.nonzero(labels == left)[1].mean()
    assert gap > 480 * 0.1  # side by side
    assert image[labels == left][:, 0].mean() > image[labels == left][:, 2].mean()  # red left
    assert image[labels == right][:, 2].mean() > image[labels == right][:, 0].mean()  # blue
    orange = (image[..., 0] > 0.8) & (np.abs(image[..., 1] - 0.35) < 0.15) & (image[..., 2] < 0.2)
    assert orange.sum() > 5  # the highlighted frustum


def test_viewer_looks_from_the_edited_view():
    cams = _ring(8, 25.0, 2.5)
    front = view_direction(cams, cams[3])
    c = cams[3].center
    assert np.isclose(np.arctan2(front[1], front[0]), np.arctan2(c[1], c[0]))
    assert np.isclose(np.linalg.norm(front), 1.0)
    assert np.isclose(np.degrees(np.arcsin(front[2])), 25.0, atol=0.5)  # the ring's elevation
    # eye on -y looking at the origin with +z up: +x is right on screen
    np.testing.assert_allclose(screen_right(np.array([0, -1.0, 0.2]), np.array([0, 0, 1.0])),
                               [1.0, 0.0, 0.0], atol=1e-12)  # fmt: skip


def test_sine_view_screenshot_and_no_display(tiny_fitted_run, tmp_path, monkeypatch):
    shot = tmp_path / "shot.png"
    argv = ["view", str(tiny_fitted_run), "--screenshot", str(shot), "--width", "320"]
    assert sine_cli.main(argv + ["--height", "240", "--device", "cpu"]) == 0
    regions, _ = _regions(read_image(shot))
    assert len(regions) == 1  # the template alone (frustums are thin lines)
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    assert sine_cli.main(["view", str(tiny_fitted_run)]) == 2  # says to use --screenshot


def test_image_metrics_on_pixel_sets():
    gt = np.full((32, 32, 3), 0.5, np.float32)
    pred = gt.copy()
    region = np.zeros((32, 32), bool)
    region[8:16, 8:16] = True
    pred[region] += 0.1  # MSE 0.01 inside: 20 dB
    obj = np.zeros_like(region)
    obj[4:20, 4:20] = True
    m = image_metrics(pred, gt, {"object": obj, "region": region, "outside_region": obj & ~region})
    assert m["psnr_region"] == pytest.approx(20.0, abs=1e-4)
    assert m["psnr_object"] == pytest.approx(20.0 + 10 * np.log10(256 / 64), abs=1e-4)
    assert m["psnr"] == pytest.approx(20.0 + 10 * np.log10(1024 / 64), abs=1e-4)
    assert m["psnr_outside_region"] == pytest.approx(120.0)  # identical pixels (MSE floor)
    assert m["ssim_outside_region"] > m["ssim_region"]


def test_to_run_frame_applies_the_normalization():
    R = np.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    run = CameraSet([], scale=0.5, center=np.array([1.0, 2.0, 3.0]), rotation=R)
    cam = Camera(16, 16, 20, 20, 8, 8, look_at([5.0, 2.0, 3.0], [1.0, 2.0, 3.0]))
    moved = to_run_frame(cam, run)
    np.testing.assert_allclose(moved.center, [0.0, 2.0, 0.0], atol=1e-12)  # 0.5 * R @ (4, 0, 0)
    np.testing.assert_allclose(moved.project(np.zeros((1, 3)))[0], [[8.0, 8.0]], atol=1e-9)


def test_sine_eval_template_against_its_captures(tiny_fitted_run, tmp_path):
    regions = tmp_path / "regions"  # the object masks as "edit region"
    shutil.copytree(tiny_fitted_run / "masks", regions)
    out = tmp_path / "eval.json"
    argv = ["eval", str(tiny_fitted_run), "--region-masks", str(regions), "--out", str(out)]
    assert sine_cli.main(argv + ["--split", "test", "--quiet", "--device", "cpu"]) == 0
    result = json.loads(out.read_text())
    assert result["mean"]["n_views"] == 1 and result["scene"] == "template"
    assert result["supersample"] == 2
    view = result["views"][0]
    assert view["name"] == "r_007.png"
    for key in ("psnr", "ssim", "psnr_object", "ssim_object", "psnr_region"):
        assert np.isfinite(view[key])
    assert view["psnr"] > view["psnr_object"] > 8.0  # the white background is easy
    # object = region (GT mask) + outside (rendered opacity only): its MSE lies between theirs
    lo, hi = sorted([view["psnr_region"], view["psnr_outside_region"]])
    assert lo <= view["psnr_object"] <= hi


def test_eval_reference_render_scores_high(tiny_fitted_run, tmp_path):
    """Ground truth made by rendering the template itself: PSNR is high (> 40 dB)."""
    from render.evaluation import evaluate_views, load_gt_views
    from render.io import write_image

    scene = load_scene(tiny_fitted_run, device="cpu")
    cams = load_cameras(tiny_fitted_run / "cameras.json")
    gt = tmp_path / "gt"
    frame = cams.frames[2]
    write_image(gt / "images" / "r_002.png", scene.render_view(frame)["rgb"])
    write_json(gt / "cameras.json", CameraSet([frame]).to_dict())
    result = evaluate_views(scene, load_gt_views(gt, cams), progress=False)
    assert result["mean"]["psnr"] > 40.0 and result["mean"]["ssim"] > 0.99


# ---- the edit path, through a stand-in for the editing side -------------------------------
@pytest.fixture
def fake_edit_run(tiny_fitted_run, tmp_path, monkeypatch):
    """A copy of the tiny run with RUN/edits/tall (edit.json view 2), and an editing hook whose
    scene is the template stretched 1.5x along z with red and blue swapped."""

    from edit.scene import TemplateScene, load_template_scene

    run = tmp_path / "run"
    shutil.copytree(tiny_fitted_run, run, ignore=shutil.ignore_patterns("edits", "features"))
    write_json(run / "edits" / "tall" / "edit.json", {"view": 2})

    class Tall(TemplateScene):
        def mesh(self):
            v, t = super().mesh()
            return v * [1.0, 1.0, 1.5], t

        def render_view(self, camera, chunk=16384):
            out = super().render_view(camera, chunk)
            return {**out, "rgb": out["rgb"][..., ::-1].copy()}

        def colors_at(self, points, normals=None):
            return super().colors_at(points, normals)[:, ::-1].copy()

    def load_edit_scene(run_dir, name, strength, device):
        base = load_template_scene(run_dir, device)
        return Tall(**{**vars(base), "name": name})

    import edit.scene

    monkeypatch.setattr(edit.scene, "load_edit_scene", load_edit_scene)
    return run


def test_outputs_of_an_edit(fake_edit_run, tmp_path):
    run = str(fake_edit_run)
    out = tmp_path / "cmp"
    argv = ["render", run, "--edit", "tall", "--compare", "--orbit", "3", "--out", str(out)]
    assert sine_cli.main(argv + ["--video", str(out / "cmp.mp4"), "--quiet"]) == 0
    strip = read_image(out / "compare" / "0000.png")
    assert strip.shape == (64, 130, 3)  # template | 2-pixel gap | edit
    np.testing.assert_allclose(strip[:, 66:], strip[:, :64, ::-1], atol=1 / 255)
    assert (video_info(out / "cmp.mp4")["width"], video_info(out / "cmp.mp4")["frames"]) == (130, 3)

    mesh = tmp_path / "tall.ply"
    assert sine_cli.main(["export", run, "--edit", "tall", "--out", str(mesh)]) == 0
    proxy = trimesh.load(fake_edit_run / "proxy_mesh.ply", process=False)
    np.testing.assert_allclose(
        trimesh.load(mesh, process=False).vertices, proxy.vertices * [1, 1, 1.5], atol=1e-5
    )

    shot = tmp_path / "view.png"
    argv = ["view", run, "--edit", "tall", "--screenshot", str(shot), "--width", "480"]
    assert sine_cli.main(argv + ["--height", "270"]) == 0
    image = read_image(shot)
    regions, labels = _regions(image)
    assert len(regions) == 2  # template and edited mesh, side by side
    left, right = sorted(regions, key=lambda r: np.nonzero(labels == r)[1].mean())
    height = [np.ptp(np.nonzero(labels == r)[0]) for r in (left, right)]
    assert height[1] > 1.2 * height[0]  # the edited one (on the right) is the taller
    left_rgb, right_rgb = image[labels == left].mean(0), image[labels == right].mean(0)
    assert left_rgb[0] > left_rgb[2] and right_rgb[2] > right_rgb[0]  # red and blue swapped
    orange = (image[..., 0] > 0.8) & (np.abs(image[..., 1] - 0.35) < 0.15) & (image[..., 2] < 0.2)
    assert orange.sum() > 5  # the edit's view (edit.json "view": 2) is highlighted

    report = tmp_path / "eval.json"
    argv = ["eval", run, "--edit", "tall", "--split", "test", "--out", str(report), "--quiet"]
    assert sine_cli.main(argv) == 0
    assert json.loads(report.read_text())["scene"] == "tall"
