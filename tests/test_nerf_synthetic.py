"""NeRF-synthetic (Blender) captures: `sine synth --format nerf-synthetic` writes RGBA images
with split JSONs, and `sine ingest` reads them back: alpha -> masks, RGB over the background
colour, the test (and val) views held out, the poses unchanged."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.capture_formats import detect_format
from recon.ingest import IngestConfig, ingest_capture
from recon.rundir import RunDir
from recon.synth import SynthConfig, synthesize
from recon.synth_output import NERF_SYNTHETIC_DIR
from render.cameras import OPENCV_TO_OPENGL, load_cameras
from render.errors import SineError
from render.io import read_image, read_json, read_mask

VIEWS, W, H = 16, 64, 48  # views 7 and 15 (1-based 8th, 16th) are the held-out ones
TEST = ["r_007.png", "r_015.png"]


@pytest.fixture(scope="module")
def synth(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("toycar_nerf")
    cfg = SynthConfig(
        out=out, procedural="toycar", views=VIEWS, width=W, height=H, format="nerf-synthetic"
    )
    summary = synthesize(cfg, progress=False)
    assert summary["nerf_synthetic"] == str(out / NERF_SYNTHETIC_DIR)
    return out


def _rgba(path: Path) -> np.ndarray:
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert raw is not None and raw.dtype == np.uint8 and raw.shape == (H, W, 4)
    return raw[..., [2, 1, 0, 3]]  # BGRA -> RGBA


def _ingest(synth: Path, tmp_path: Path, **options) -> tuple[RunDir, dict]:
    run = RunDir(tmp_path / "run")
    return run, ingest_capture(synth / NERF_SYNTHETIC_DIR, run, IngestConfig(**options))


# ---- the layout sine synth writes ---------------------------------------------------------
def test_synth_writes_the_blender_layout(synth):
    nerf = synth / NERF_SYNTHETIC_DIR
    cams = load_cameras(synth / "cameras.json").by_name()
    js = {
        s: json.loads((nerf / f"transforms_{s}.json").read_text()) for s in ("train", "val", "test")
    }
    names = {s: [Path(f["file_path"]).name + ".png" for f in d["frames"]] for s, d in js.items()}
    assert names["test"] == TEST and names["val"] == TEST  # val repeats the test views
    assert names["train"] == [n for n in sorted(cams) if n not in TEST]
    assert sorted(p.name for p in (nerf / "test").iterdir()) == TEST
    assert not (nerf / "val").exists()
    for split in ("train", "test"):
        for frame in js[split]["frames"]:
            assert frame["file_path"].startswith(f"./{split}/r_")  # no extension, as Blender
            cam = cams[Path(frame["file_path"]).name + ".png"]
            gl = np.array(frame["transform_matrix"])
            np.testing.assert_allclose(gl, cam.camera_to_world @ OPENCV_TO_OPENGL, atol=1e-12)
            # fov across the width: tan(angle / 2) = (W / 2) / fx
            np.testing.assert_allclose(np.tan(0.5 * js[split]["camera_angle_x"]), 0.5 * W / cam.fx)
            # RGBA: alpha = the synth mask, RGB = the synth image on the object, 0 elsewhere
            rgba = _rgba(nerf / f"{frame['file_path']}.png")
            mask = read_mask(synth / "masks" / cam.name)
            assert 0 < mask.sum() < mask.size
            np.testing.assert_array_equal(rgba[..., 3], np.where(mask, 255, 0))
            image = cv2.imread(str(synth / "images" / cam.name))[..., ::-1]
            np.testing.assert_array_equal(rgba[mask][:, :3], image[mask])
            assert (rgba[~mask][:, :3] == 0).all()


def test_default_format_writes_no_blender_layout(tmp_path):
    out = tmp_path / "out"
    synthesize(SynthConfig(out=out, procedural="toycar", views=3, width=16, height=12), False)
    assert (out / "transforms.json").is_file() and not (out / NERF_SYNTHETIC_DIR).exists()
    with pytest.raises(SineError, match="--format"):
        synthesize(SynthConfig(out=out, procedural="toycar", format="blender"), False)


# ---- ingesting it -------------------------------------------------------------------------
def test_ingest_alpha_masks_white_background_and_held_out_test_split(synth, tmp_path):
    nerf = synth / NERF_SYNTHETIC_DIR
    assert detect_format(nerf) == "transforms"
    run, summary = _ingest(synth, tmp_path)
    # val repeats the test images: 16 views, not 18
    assert (summary["views"], summary["train"], summary["test"]) == (VIEWS, VIEWS - 2, 2)
    assert summary["masks"] == summary["alpha_masks"] == VIEWS
    assert summary["background"] == [1.0, 1.0, 1.0]
    assert any("transforms_val.json repeats 2" in n for n in summary["notes"])
    assert any("composited over the background colour (1, 1, 1)" in n for n in summary["notes"])
    captures = read_json(run.captures)
    assert captures["alpha_background"] == [1.0, 1.0, 1.0]

    ref = load_cameras(synth / "cameras.json").by_name()
    got = run.load_cameras()
    assert sorted(c.name for c in got.frames) == sorted(ref)
    assert sorted(c.name for c in got.split("test")) == TEST  # = the JSON files' test frames
    for cam in got.frames:
        want = ref[cam.name]
        assert cam.split == want.split  # the synth's own split agrees with the split files
        assert (cam.width, cam.height) == (W, H)
        np.testing.assert_allclose(
            [cam.fx, cam.fy, cam.cx, cam.cy], [want.fx, want.fy, W / 2, H / 2]
        )
        np.testing.assert_allclose(cam.fx, want.fx, rtol=1e-12)
        np.testing.assert_allclose(cam.camera_to_world, want.camera_to_world, atol=1e-12)

        mask = read_mask(run.mask_path(cam.name))
        np.testing.assert_array_equal(mask, read_mask(synth / "masks" / cam.name))
        image = read_image(run.image_path(cam.name))
        synth_image = read_image(synth / "images" / cam.name)
        np.testing.assert_array_equal(image[mask], synth_image[mask])  # object: the synth colour
        assert (image[~mask] == 1.0).all()  # background: white (the RGBA stores 0 there)


def test_fit_reads_the_held_out_views(synth, tmp_path):
    from recon.fit_data import load_views

    run, _ = _ingest(synth, tmp_path)
    test = load_views(run, "test")
    assert sorted(cam.name for cam, _, _ in test) == TEST
    assert all(mask is not None and mask.any() for _, _, mask in test)
    assert len(load_views(run, "train")) == VIEWS - 2


@pytest.mark.parametrize(
    "colour, want", [(["black"], [0.0, 0.0, 0.0]), (["0.2", "0.4", "1"], [0.2, 0.4, 1.0])]
)
def test_background_color_option(synth, tmp_path, colour, want):
    run, summary = _ingest(synth, tmp_path, background_color=colour)
    assert summary["background"] == want
    image = read_image(run.image_path("r_003.png"))
    mask = read_mask(run.mask_path("r_003.png"))
    np.testing.assert_allclose(
        image[~mask], np.broadcast_to(want, image[~mask].shape), atol=0.5 / 255
    )


def test_cli_background_color_and_bad_values(synth, tmp_path, capsys):
    from sine_cli import main

    out = tmp_path / "run"
    args = ["ingest", str(synth / NERF_SYNTHETIC_DIR), "--out", str(out)]
    assert main([*args, "--background-color", "black"]) == 0
    printed = capsys.readouterr().out
    assert "14 train / 2 test" in printed and "background colour (0, 0, 0)" in printed
    assert (read_image(out / "images" / "r_000.png")[0, 0] == 0).all()
    for bad in (["grey"], ["1", "1"], ["0", "0", "2"]):
        assert main([*args, "--background-color", *bad]) == 2
        assert "--background-color" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["ingest", "--help"])
    assert "--background-color" in capsys.readouterr().out


def test_one_split_file_reads_that_file_alone(synth, tmp_path):
    """CAPTURE/transforms_train.json: its frames only, held out by the every-8th rule."""
    run = RunDir(tmp_path / "run")
    summary = ingest_capture(synth / NERF_SYNTHETIC_DIR / "transforms_train.json", run)
    assert (summary["views"], summary["test"]) == (VIEWS - 2, 1)
    assert summary["alpha_masks"] == VIEWS - 2
    held_out = [c.name for c in run.load_cameras().split("test")]
    assert held_out == ["r_008.png"]  # the 8th frame of the train file


def test_distinct_val_images_are_held_out_too(synth, tmp_path):
    """A Blender folder whose val/ has its own images (named like the test ones): every view
    is kept, val and test both held out, the clashing stems prefixed by their folder."""
    cap = tmp_path / "cap"
    shutil.copytree(synth / NERF_SYNTHETIC_DIR, cap)
    shutil.copytree(cap / "test", cap / "val")
    val = json.loads((cap / "transforms_val.json").read_text())
    for frame in val["frames"]:
        frame["file_path"] = frame["file_path"].replace("./test/", "./val/")
    (cap / "transforms_val.json").write_text(json.dumps(val))
    run = RunDir(tmp_path / "run")
    summary = ingest_capture(cap, run)
    assert (summary["views"], summary["train"], summary["test"]) == (VIEWS + 2, VIEWS - 2, 4)
    held_out = sorted(c.name for c in run.load_cameras().split("test"))
    assert held_out == ["test_r_007.png", "test_r_015.png", "val_r_007.png", "val_r_015.png"]


def test_split_files_without_train_file_are_refused(synth, tmp_path):
    cap = tmp_path / "cap"
    cap.mkdir()
    shutil.copy(synth / NERF_SYNTHETIC_DIR / "transforms_test.json", cap)
    with pytest.raises(SineError, match="neither transforms.json nor transforms_train.json"):
        detect_format(cap)
