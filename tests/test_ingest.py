"""recon/ingest.py + `sine ingest`: every capture format into a run directory, and the errors."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.capture_formats import detect_format
from recon.ingest import IngestConfig, assign_splits, ingest_capture
from recon.rundir import RunDir
from render import cameras as C
from render.errors import SineError
from render.io import read_depth, read_image, read_json, read_mask, read_yaml, write_image

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
TEMPLE = DATA / "middlebury-templeSparseRing"
DINO = DATA / "oxford-dinosaur"
# templeSparseRing README: tight bounding box of the object
TEMPLE_BBOX = np.array([[-0.073568, 0.021728, -0.012445], [0.028855, 0.181892, 0.062736]])

W, H = 64, 48  # source size of the synthetic captures


# ---- synthetic captures -------------------------------------------------------------------
def ring_cameras(n: int = 4, width: int = W, height: int = H) -> list[C.Camera]:
    cams = []
    for i in range(n):
        a = 2 * np.pi * i / n
        c2w = C.look_at([3 * np.cos(a), 3 * np.sin(a), 1.0], [0, 0, 0])
        f = 60.0 * width / W
        cams.append(C.Camera(width, height, f, f, width / 2, height / 2, c2w, name=f"v{i}.png"))
    return cams


def pattern(i: int, width: int = W, height: int = H) -> np.ndarray:
    """A distinct smooth RGB image per view (float [H, W, 3])."""
    v, u = np.mgrid[0:height, 0:width] / np.array([height, width])[:, None, None]
    return np.stack([u, v, np.full_like(u, 0.1 * i)], axis=2).astype(np.float32)


def rect_mask(width: int = W, height: int = H) -> np.ndarray:
    m = np.zeros((height, width), np.uint8)
    m[12:36, 16:48] = 255
    return m


def depth_map(i: int) -> np.ndarray:
    d = np.zeros((H, W), np.float32)
    d[12:36, 16:48] = 2.0 + 0.25 * i
    d[12:24, 16:32] = 2.5 + 0.25 * i
    return d


def make_transforms(root: Path, n: int = 4, masks=True, depth=True) -> list[C.Camera]:
    cams = ring_cameras(n)
    (root / "images").mkdir(parents=True)
    paths = []
    for i, cam in enumerate(cams):
        write_image(root / "images" / cam.name, pattern(i))
        paths.append(f"images/{cam.name}")
    data = C.cameras_to_transforms(cams, paths)
    for i, frame in enumerate(data["frames"]):
        if masks:
            (root / "masks").mkdir(exist_ok=True)
            cv2.imwrite(str(root / "masks" / f"v{i}.png"), rect_mask())
            frame["mask_path"] = f"masks/v{i}.png"
        if depth:
            (root / "depth").mkdir(exist_ok=True)
            np.save(root / "depth" / f"v{i}.npy", depth_map(i))
            frame["depth_file_path"] = f"depth/v{i}.npy"
    (root / "transforms.json").write_text(json.dumps(data))
    return cams


def image_folder(root: Path, n: int = 4, size=(W, H), suffix=".png") -> Path:
    root.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        write_image(root / f"img_{i:03d}{suffix}", pattern(i, *size))
    return root


def assert_camera_close(a: C.Camera, b: C.Camera, atol=1e-6):
    assert (a.width, a.height) == (b.width, b.height)
    np.testing.assert_allclose([a.fx, a.fy, a.cx, a.cy], [b.fx, b.fy, b.cx, b.cy], atol=atol)
    np.testing.assert_allclose(a.camera_to_world, b.camera_to_world, atol=atol)


# ---- splits -------------------------------------------------------------------------------
def test_assign_splits():
    splits = assign_splits(16, 8)
    assert [i for i, s in enumerate(splits) if s == "test"] == [7, 15]
    assert assign_splits(5, 8) == ["train"] * 5
    assert assign_splits(3, 0) == ["train"] * 3
    assert assign_splits(4, 2) == ["train", "test", "train", "test"]
    for bad in (1, -2):
        with pytest.raises(SineError, match="holdout_every"):
            assign_splits(4, bad)


# ---- shared data ----------------------------------------------------------------------------
def test_temple_sparse_ring(tmp_path):
    if not TEMPLE.is_dir():
        pytest.skip("shared data missing")
    from sine_cli import main

    run = RunDir(tmp_path / "run")
    assert main(["ingest", str(TEMPLE), "--out", str(run.root), "--width", "320"]) == 0
    cams = run.load_cameras()
    assert len(cams.frames) == 16
    assert [c.split for c in cams.frames].count("test") == 2
    centre = TEMPLE_BBOX.mean(axis=0)
    rows = {name: (K, R, t) for name, K, R, t in C.read_middlebury_par(TEMPLE / "templeSR_par.txt")}
    for cam in cams.frames:
        assert (cam.width, cam.height) == (320, 240)
        img = read_image(run.image_path(cam.name))
        assert img.shape == (240, 320, 3)
        # the object's centre is seen by every camera, in front of it and inside the image
        uv, z = cam.project(centre)
        assert z[0] > 0
        assert 0 < uv[0, 0] < cam.width and 0 < uv[0, 1] < cam.height
        # intrinsics follow the resize exactly: x = K[R|t]X at 640x480, halved
        K, R, t = rows[cam.name]
        x = K @ (R @ centre + t)
        np.testing.assert_allclose(uv[0], x[:2] / x[2] / 2, atol=1e-6)
        assert cam.fx == pytest.approx(1520.4 / 2)
        assert not cam.distortion.any()
    captures = read_json(run.captures)
    assert captures["format"] == "middlebury" and captures["poses"] is True
    rec = captures["images"][0]
    assert (rec["source_width"], rec["source_height"], rec["width"], rec["height"]) == (
        640,
        480,
        320,
        240,
    )
    assert len(rec["sha256"]) == 64 and rec["status"] == "ok"
    config = read_yaml(run.config)
    assert config["stages"][0]["stage"] == "ingest"
    assert config["stages"][0]["config"]["width"] == 320

    # idempotent: the same capture and options is skipped, --force redoes it
    mtime = run.image_path("templeSR0001.png").stat().st_mtime_ns
    summary = ingest_capture(TEMPLE, run, IngestConfig(width=320))
    assert summary["skipped"] and summary["views"] == 16
    assert run.image_path("templeSR0001.png").stat().st_mtime_ns == mtime
    summary = ingest_capture(TEMPLE, run, IngestConfig(width=320, force=True))
    assert not summary["skipped"]
    # other options: redone, and the camera follows the new size
    summary = ingest_capture(TEMPLE, run, IngestConfig(width=160, ignore_poses=True))
    assert not summary["skipped"] and not summary["poses"]
    assert not run.cameras.exists()
    assert read_image(run.image_path("templeSR0001.png")).shape == (120, 160, 3)


def test_oxford_dinosaur_images_without_poses(tmp_path):
    if not DINO.is_dir():
        pytest.skip("shared data missing")
    run = RunDir(tmp_path / "run")
    summary = ingest_capture(DINO, run, IngestConfig(width=64))
    assert summary["format"] == "images" and summary["views"] == 36
    assert summary["working_size"] == "64x51" and summary["source_size"] == "720x576"
    assert not run.cameras.exists()
    assert any("dino_Ps.mat" in note for note in summary["notes"])
    assert len(list(run.images.glob("*.png"))) == 36
    assert read_image(run.image_path("viff.000.png")).shape == (51, 64, 3)


# ---- transforms.json with masks and depth --------------------------------------------------
def test_transforms_with_masks_and_depth(tmp_path):
    cams = make_transforms(tmp_path / "cap")
    assert detect_format(tmp_path / "cap") == "transforms"
    run = RunDir(tmp_path / "run")
    summary = ingest_capture(tmp_path / "cap", run, IngestConfig(width=32, holdout_every=2))
    assert summary["poses"] and summary["masks"] == 4 and summary["depth"] == 4
    assert (summary["train"], summary["test"]) == (2, 2)
    got = run.load_cameras().by_name()
    for i, cam in enumerate(cams):
        assert_camera_close(got[cam.name], cam.resized(32, 24))
        img = read_image(run.image_path(cam.name))
        np.testing.assert_allclose(
            img, cv2.resize(pattern(i), (32, 24), interpolation=cv2.INTER_AREA), atol=1 / 255
        )
        mask = read_mask(run.mask_path(cam.name))
        expected = np.zeros((24, 32), bool)
        expected[6:18, 8:24] = True
        np.testing.assert_array_equal(mask, expected)
        depth = read_depth(run.depth_path(cam.name))
        assert depth.shape == (24, 32) and depth.dtype == np.float32
        assert set(np.unique(depth)) <= set(np.unique(depth_map(i)))  # values unchanged
        assert depth[6, 8] == pytest.approx(2.5 + 0.25 * i) and depth[0, 0] == 0

    # user masks always win over the capture's own
    user = tmp_path / "user_masks"
    user.mkdir()
    for cam in cams:
        cv2.imwrite(str(user / cam.name), np.full((H, W), 255, np.uint8))
    ingest_capture(tmp_path / "cap", run, IngestConfig(width=32, masks=user))
    assert read_mask(run.mask_path(cams[0].name)).all()

    # --ignore-poses keeps images, masks and depth, but no cameras.json
    summary = ingest_capture(tmp_path / "cap", run, IngestConfig(width=32, ignore_poses=True))
    assert not run.cameras.exists() and summary["masks"] == 4 and summary["depth"] == 4


def test_transforms_nerf_blender_form(tmp_path):
    """camera_angle_x, file paths without extension, RGBA images: alpha becomes the mask."""
    root = tmp_path / "cap"
    (root / "train").mkdir(parents=True)
    cams = ring_cameras(3)
    frames = []
    for i, cam in enumerate(cams):
        rgba = np.zeros((H, W, 4), np.uint8)
        rgba[..., :3] = (pattern(i) * 255).astype(np.uint8)
        rgba[..., 3] = rect_mask()
        cv2.imwrite(str(root / "train" / f"r_{i}.png"), rgba)
        gl = cam.camera_to_world @ C.OPENCV_TO_OPENGL
        frames.append({"file_path": f"./train/r_{i}", "transform_matrix": gl.tolist()})
    angle = 2 * np.arctan(0.5 * W / cams[0].fx)
    (root / "transforms_train.json").write_text(
        json.dumps({"camera_angle_x": angle, "frames": frames})
    )
    assert detect_format(root) == "transforms"  # a folder with split files: NeRF synthetic
    for capture in (root, root / "transforms_train.json"):
        run = RunDir(tmp_path / "runs" / capture.name)  # beside the capture, not in it
        summary = ingest_capture(capture, run, IngestConfig(width=64))
        assert summary["views"] == summary["train"] == 3
        assert summary["masks"] == summary["alpha_masks"] == 3
        got = run.load_cameras().by_name()
        for cam, i in zip(cams, range(3), strict=True):
            assert_camera_close(got[f"r_{i}.png"], cam)
            mask = rect_mask() > 0
            np.testing.assert_array_equal(read_mask(run.mask_path(f"r_{i}.png")), mask)
            image = read_image(run.image_path(f"r_{i}.png"))  # composited over white
            source = cv2.imread(str(root / "train" / f"r_{i}.png"))[..., ::-1] / 255.0
            np.testing.assert_allclose(image[mask], source[mask], atol=1e-6)
            assert (image[~mask] == 1.0).all()
    (root / "transforms_train.json").rename(root / "transforms_test.json")
    with pytest.raises(SineError, match="transforms_test.json"):
        detect_format(root)


def test_undistortion_moves_points_to_the_pinhole_projection(tmp_path):
    """A dot drawn where a distorted camera sees a 3D point ends up where the ingested (pinhole,
    resized) camera projects it."""
    cam = ring_cameras(1, 160, 120)[0].replace(distortion=np.array([-0.3, 0.05, 0.001, -0.001]))
    # points seen (without distortion) near two corners and at the centre of the image
    origins, dirs = cam.rays(np.array([[22.0, 18.0], [136.0, 100.0], [80.0, 60.0]]))
    points = origins + 3.0 * dirs
    K_cv = cam.K.copy()
    K_cv[:2, 2] -= 0.5  # OpenCV: pixel centres at integers
    w2c = cam.world_to_camera
    rvec = cv2.Rodrigues(w2c[:3, :3])[0]
    uv_dist = cv2.projectPoints(points, rvec, w2c[:3, 3], K_cv, cam.distortion)[0][:, 0] + 0.5
    v, u = np.mgrid[0:120, 0:160] + 0.5
    img = np.zeros((120, 160), np.float32)
    for x, y in uv_dist:
        img += np.exp(-((u - x) ** 2 + (v - y) ** 2) / (2 * 1.5**2))
    root = tmp_path / "cap"
    (root / "images").mkdir(parents=True)
    frames = []
    for i in range(3):
        write_image(root / "images" / f"d{i}.png", np.repeat(img[..., None], 3, axis=2))
        frames.append(f"images/d{i}.png")
    (root / "transforms.json").write_text(json.dumps(C.cameras_to_transforms([cam] * 3, frames)))
    run = RunDir(tmp_path / "run")
    summary = ingest_capture(root, run, IngestConfig(width=80))
    assert summary["undistorted"] == 3
    out_cam = run.load_cameras().by_name()["d0.png"]
    assert not out_cam.distortion.any() and (out_cam.width, out_cam.height) == (80, 60)
    out = read_image(run.image_path("d0.png"))[..., 0]
    uv, _ = out_cam.project(points)
    assert np.abs(uv_dist[0] / 2 - uv[0]).max() > 1.5  # distortion mattered for this point
    vv, uu = np.mgrid[0:60, 0:80] + 0.5
    for x, y in uv:
        win = (np.abs(uu - x) < 4) & (np.abs(vv - y) < 4)
        wts = out * win
        centroid = np.array([(wts * uu).sum(), (wts * vv).sum()]) / wts.sum()
        np.testing.assert_allclose(centroid, [x, y], atol=0.35)


# ---- other formats ---------------------------------------------------------------------------
def test_colmap_model(tmp_path):
    cams = ring_cameras(3)
    root = tmp_path / "proj"
    image_folder(root / "images", 0)
    for i, cam in enumerate(cams):
        write_image(root / "images" / cam.name, pattern(i))
    C.write_colmap_text(root / "sparse" / "0", cams)
    assert detect_format(root) == "colmap"
    for capture in (root, root / "sparse" / "0"):
        run = RunDir(tmp_path / f"run_{capture.name}")
        summary = ingest_capture(capture, run, IngestConfig(width=32))
        assert summary["format"] == "colmap" and summary["views"] == 3
        got = run.load_cameras().by_name()
        for cam in cams:
            assert_camera_close(got[cam.name], cam.resized(32, 24))


def test_middlebury_neus_and_projection_formats(tmp_path):
    cams = ring_cameras(3)
    # Middlebury ring
    mid = tmp_path / "mid"
    mid.mkdir()
    for i, cam in enumerate(cams):
        write_image(mid / cam.name, pattern(i))
    C.write_middlebury_par(mid / "obj_par.txt", cams)
    # NeuS / IDR
    neus = tmp_path / "neus"
    (neus / "image").mkdir(parents=True)
    (neus / "mask").mkdir()
    for i in range(3):
        write_image(neus / "image" / f"{i:03d}.png", pattern(i))
        cv2.imwrite(str(neus / "mask" / f"{i:03d}.png"), rect_mask())
    scale_mat = np.diag([0.5, 0.5, 0.5, 1.0])
    scale_mat[:3, 3] = [0.1, 0.2, 0.3]
    np.savez(neus / "cameras_sphere.npz", **C.cameras_to_neus(cams, scale_mat))
    # images + 3x4 projection matrices (one negatively scaled, one with a text header)
    prj = tmp_path / "prj"
    prj.mkdir()
    for i, cam in enumerate(cams):
        write_image(prj / f"p{i}.jpg", pattern(i))
        P = cam.projection * (-2.0 if i == 1 else 1.0)
        text = "\n".join(" ".join(repr(float(x)) for x in row) for row in P)
        if i == 2:
            (prj / f"p{i}.P").write_text("CONTOUR\n" + text)
        else:
            (prj / f"p{i}_P.txt").write_text(text)

    for root, fmt in ((mid, "middlebury"), (neus, "neus"), (prj, "projections")):
        assert detect_format(root) == fmt
        run = RunDir(tmp_path / f"run_{fmt}")
        summary = ingest_capture(root, run, IngestConfig(width=32, holdout_every=0))
        assert summary["format"] == fmt and summary["views"] == 3 and summary["test"] == 0
        frames = run.load_cameras().frames
        for cam, got in zip(cams, frames, strict=True):
            assert_camera_close(got, cam.resized(32, 24), atol=1e-6)
    assert summary["masks"] == 0
    assert detect_format(mid / "obj_par.txt") == "middlebury"
    assert detect_format(neus / "cameras_sphere.npz") == "neus"
    neus_cams = RunDir(tmp_path / "run_neus").load_cameras()
    norm = neus_cams.extra["source_normalization"]
    assert norm["scale"] == pytest.approx(2.0) and norm["center"] == pytest.approx([0.1, 0.2, 0.3])
    assert len(list(RunDir(tmp_path / "run_neus").masks.glob("*.png"))) == 3


def test_video(tmp_path):
    path = tmp_path / "turn.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 10, (W, H))
    assert writer.isOpened()
    for i in range(20):
        writer.write(np.full((H, W, 3), 10 * i, np.uint8))
    writer.release()
    assert detect_format(path) == "video"
    run = RunDir(tmp_path / "run")
    summary = ingest_capture(path, run, IngestConfig(width=32, frames=5))
    assert summary["format"] == "video" and summary["views"] == 5 and not summary["poses"]
    names = [r["name"] for r in read_json(run.captures)["images"]]
    # 5 frames evenly over 0..19: 0, 5, 10 (9.5 rounds to even), 14, 19
    assert names == [f"turn_{i:05d}.png" for i in (0, 5, 10, 14, 19)]
    for name, i in zip(names, (0, 5, 10, 14, 19), strict=True):
        img = read_image(run.image_path(name))
        assert img.shape == (24, 32, 3)
        assert img.mean() * 255 == pytest.approx(10 * i, abs=3)


# ---- errors --------------------------------------------------------------------------------
def test_errors(tmp_path):
    run = RunDir(tmp_path / "run")

    def fails(capture, match, **options):
        with pytest.raises(SineError, match=match):
            ingest_capture(capture, run, IngestConfig(**{"width": 32, **options}))

    fails(tmp_path / "nope", "does not exist")
    (tmp_path / "empty").mkdir()
    fails(tmp_path / "empty", "is empty")
    # non-image and unreadable files are listed by name
    notes = tmp_path / "notes"
    notes.mkdir()
    (notes / "a.doc").write_text("x")
    fails(notes, "no images found.*a.doc")
    odd = image_folder(tmp_path / "odd")
    (odd / "photo.heic").write_bytes(b"\0" * 16)
    fails(odd, "not images.*photo.heic")
    broken = image_folder(tmp_path / "broken")
    (broken / "bad.png").write_bytes(b"not a png")
    (broken / "worse.jpg").write_bytes(b"")
    fails(broken, "cannot read.*bad.png.*worse.jpg")
    fails(image_folder(tmp_path / "two", n=2), "only 2 view.*at least 3")
    # a video that cannot be opened
    (tmp_path / "clip.mp4").write_bytes(b"definitely not a video")
    fails(tmp_path / "clip.mp4", "cannot open video")
    # unknown camera formats
    (tmp_path / "other.json").write_text(json.dumps({"hello": 1}))
    fails(tmp_path / "other.json", "unknown camera format")
    (tmp_path / "calib.txt").write_text("1 2 3")
    fails(tmp_path / "calib.txt", "unknown camera format")
    fails(image_folder(tmp_path / "imgs"), "unknown camera format", format="bogus")
    fails(tmp_path / "imgs", "no COLMAP model", format="colmap")
    # mixed sizes without per-image intrinsics
    mixed = image_folder(tmp_path / "mixed")
    write_image(mixed / "z_big.png", pattern(0, 80, 60))
    fails(mixed, "mixed sizes.*64x48: 4.*80x60: 1.*per-image")
    # a --masks folder that misses some images
    masks = tmp_path / "masks"
    masks.mkdir()
    cv2.imwrite(str(masks / "img_000.png"), rect_mask())
    fails(tmp_path / "imgs", "no mask for 3 of 4.*img_001", masks=masks)
    fails(tmp_path / "imgs", "not a folder", masks=tmp_path / "nomasks")
    # a transforms.json pointing at missing images: fewer than 3 left is an error
    make_transforms(tmp_path / "tf", masks=False, depth=False)
    (tmp_path / "tf" / "images" / "v1.png").unlink()
    (tmp_path / "tf" / "images" / "v2.png").unlink()
    fails(tmp_path / "tf", "lists 4 images but only 2 exist.*v1.png, images/v2.png")
    fails(tmp_path / "imgs", "--width", width=4)
    assert not run.captures.exists()


# ---- lenient ingestion --------------------------------------------------------------------
def test_pose_files_listing_missing_images_keep_the_ones_present(tmp_path, capsys):
    cams = ring_cameras(5)
    mid = tmp_path / "mid"
    mid.mkdir()
    for i, cam in enumerate(cams):
        write_image(mid / cam.name, pattern(i))
    C.write_middlebury_par(mid / "obj_par.txt", cams)
    (mid / "v1.png").unlink()
    (mid / "v3.png").unlink()
    run = RunDir(tmp_path / "run")
    summary = ingest_capture(mid, run, IngestConfig(width=32, holdout_every=0))
    assert summary["views"] == 3 and summary["poses"]
    assert any("2 image(s) listed in obj_par.txt do not exist (v1.png, v3.png)" in n
               for n in summary["notes"])  # fmt: skip
    assert "[ingest] warning: 2 image(s)" in capsys.readouterr().out
    got = run.load_cameras().by_name()
    assert sorted(got) == ["v0.png", "v2.png", "v4.png"]
    for i in (0, 2, 4):
        assert_camera_close(got[f"v{i}.png"], cams[i].resized(32, 24))
    # the same with --ignore-poses: no cameras.json, intrinsics of the three kept
    run2 = RunDir(tmp_path / "run2")
    summary = ingest_capture(mid, run2, IngestConfig(width=32, ignore_poses=True))
    assert summary["views"] == 3 and not run2.cameras.exists()
    assert all("intrinsics" in r for r in run2.load_captures()["images"])
    # a transforms.json with a missing frame and a COLMAP model with a missing image
    make_transforms(tmp_path / "tf", masks=False, depth=False)
    (tmp_path / "tf" / "images" / "v2.png").unlink()
    summary = ingest_capture(tmp_path / "tf", RunDir(tmp_path / "run3"), IngestConfig(width=32))
    assert summary["views"] == 3 and "images/v2.png" in " ".join(summary["notes"])
    col = tmp_path / "col"
    (col / "images").mkdir(parents=True)
    for i, cam in enumerate(cams[:4]):
        write_image(col / "images" / cam.name, pattern(i))
    C.write_colmap_text(col / "sparse" / "0", cams)  # lists v4.png, absent
    summary = ingest_capture(col, RunDir(tmp_path / "run4"), IngestConfig(width=32))
    assert summary["views"] == 4 and "v4.png" in " ".join(summary["notes"])


def test_ignore_poses_does_not_need_a_usable_pose_file(tmp_path):
    mid = image_folder(tmp_path / "mid")
    (mid / "obj_par.txt").write_text("2\nimg_000.png 1 2 3\n")  # truncated: unusable
    with pytest.raises(SineError):
        ingest_capture(mid, RunDir(tmp_path / "run"), IngestConfig(width=32))
    run = RunDir(tmp_path / "run2")
    summary = ingest_capture(mid, run, IngestConfig(width=32, ignore_poses=True))
    assert summary["views"] == 4 and summary["format"] == "images" and not summary["poses"]
    assert any("middlebury cameras could not be used" in n for n in summary["notes"])
    assert not any("intrinsics" in r for r in run.load_captures()["images"])


def test_projection_files_match_images_by_their_number(tmp_path):
    """`00012_P.txt` beside `00012._c.png` (a suffix after the number) is that image's camera."""
    cams = ring_cameras(3)
    prj = tmp_path / "prj"
    prj.mkdir()
    for i, cam in enumerate(cams):
        write_image(prj / f"{i:05d}._c.png", pattern(i))
        text = "\n".join(" ".join(repr(float(x)) for x in row) for row in cam.projection)
        (prj / f"{i:05d}_P.txt").write_text(text)
    assert detect_format(prj) == "projections"
    run = RunDir(tmp_path / "run")
    summary = ingest_capture(prj, run, IngestConfig(width=32, holdout_every=0))
    assert summary["format"] == "projections" and summary["views"] == 3
    for cam, got in zip(cams, run.load_cameras().frames, strict=True):
        assert_camera_close(got, cam.resized(32, 24), atol=1e-6)
    # two images with one number share a file: ambiguous, an error
    write_image(prj / "00001._d.png", pattern(5))
    with pytest.raises(SineError, match="same projection file.*00001_P.txt"):
        ingest_capture(prj, RunDir(tmp_path / "run2"), IngestConfig(width=32))


def test_jpeg_exif_orientation_is_applied(tmp_path):
    """A phone photo stored landscape with orientation 6 (turn 90 degrees clockwise to view) is
    ingested upright: portrait, the stored top-left corner at the top right."""
    from PIL import Image

    folder = tmp_path / "phone"
    folder.mkdir()
    for i in range(3):
        stored = np.zeros((40, 60, 3), np.uint8)  # landscape as stored: H 40, W 60
        stored[:10, :10] = (255, 0, 0)  # red block at the stored top-left
        exif = Image.Exif()
        exif[0x0112] = 6
        Image.fromarray(stored).save(folder / f"p{i}.jpg", exif=exif, quality=95)
    run = RunDir(tmp_path / "run")
    summary = ingest_capture(folder, run, IngestConfig(width=400))
    assert summary["working_size"] == "40x60" and summary["source_size"] == "40x60"
    image = read_image(run.image_path("p0.png"))
    assert image.shape == (60, 40, 3)
    assert image[2:8, 32:38, 0].mean() > 0.8 and image[2:8, 2:8, 0].mean() < 0.2


def test_cli_help_lists_every_option(capsys):
    from sine_cli import build_parser

    with pytest.raises(SystemExit):
        build_parser(["ingest"]).parse_args(["ingest", "--help"])
    out = capsys.readouterr().out
    for flag in ("--out", "--width", "--frames", "--holdout-every", "--format", "--ignore-poses",
                 "--masks", "--background-color", "--force"):  # fmt: skip
        assert flag in out


def high_frequency_energy(image: np.ndarray) -> float:
    """Mean squared Laplacian of the image's inner part (no border effects)."""
    return float((cv2.Laplacian(image.astype(np.float32), cv2.CV_32F)[8:-8, 8:-8] ** 2).mean())


def test_undistortion_keeps_the_photos_fine_texture(tmp_path):
    """A mild distortion shifts pixels by fractions of a pixel (here 0.4 on average); resampling
    must not blur the photo (of a fine texture's Laplacian energy bilinear keeps 62 %, Lanczos
    94 %), in both places images are undistorted: at ingest (the capture's distortion) and after
    SfM estimated one (`undistort_in_place`)."""
    from recon.poses import undistort_in_place

    noise = np.random.default_rng(0).uniform(0.2, 0.8, (96, 128)).astype(np.float32)
    noise = np.repeat(cv2.GaussianBlur(noise, (0, 0), 0.6)[..., None], 3, axis=2)
    cam = ring_cameras(1, 128, 96)[0]
    dist = np.array([0.05, 0.0, 0.0, 0.0])

    path = tmp_path / "photo.png"
    write_image(path, noise)
    before = read_image(path)
    undistort_in_place([path], cam, dist, nearest=False)
    after_sfm = read_image(path)
    assert not np.allclose(after_sfm, before)  # the pixels did move
    assert high_frequency_energy(after_sfm) > 0.85 * high_frequency_energy(noise)

    root = tmp_path / "cap"
    (root / "images").mkdir(parents=True)
    frames = []
    for i in range(3):
        write_image(root / "images" / f"n{i}.png", noise)
        frames.append(f"images/n{i}.png")
    cams = [cam.replace(distortion=dist)] * 3
    (root / "transforms.json").write_text(json.dumps(C.cameras_to_transforms(cams, frames)))
    run = RunDir(tmp_path / "run")
    assert ingest_capture(root, run, IngestConfig(width=128))["undistorted"] == 3
    ingested = read_image(run.image_path("n0.png"))
    assert high_frequency_energy(ingested) > 0.85 * high_frequency_energy(noise)
    assert ingested.min() >= 0.0 and ingested.max() <= 1.0
