"""Editing targets without a 2D editor: TPS warp, scale, stretch, recolour, paint; the
`sine snapshot` / `sine target` commands on a tiny fitted run."""

from __future__ import annotations

import numpy as np
import pytest
from feature_run_helpers import tiny_feature_run

from edit import targets
from edit.target_cli import parse_color, parse_points, parse_warp
from render.errors import SineError
from render.io import read_image, read_image_rgba, read_label_map, read_mask, write_mask
from sine_cli import main

WHITE = np.ones(3, np.float32)


def _scene(size=96):
    """White background, a grey 40x40 object (rows/cols 20..59) with a red 3x3 blob centred at
    (x, y) = (30, 30), a blue 6x6 object near the bottom-right corner (rows/cols 80..85)."""
    image = np.ones((size, size, 3), np.float32)
    alpha = np.zeros((size, size), np.float32)
    image[20:60, 20:60] = 0.5
    alpha[20:60, 20:60] = 1.0
    image[29:32, 29:32] = (1.0, 0.0, 0.0)
    image[80:86, 80:86] = (0.0, 0.0, 1.0)
    alpha[80:86, 80:86] = 1.0
    return image, alpha


def _red_centre(image):
    red = (image[..., 0] > 0.7) & (image[..., 1] < 0.3) & (image[..., 2] < 0.3)
    ys, xs = np.nonzero(red)
    assert len(xs) > 0
    return xs.mean(), ys.mean()


# ---- warp ---------------------------------------------------------------------------------
def test_tps_map_reads_handle_source_at_target_and_keeps_anchors():
    handles = [((30.0, 30.0), (40.0, 36.0))]
    anchors = [(82.0, 82.0)] + targets.border_points(96, 96)
    map_x, map_y = targets.tps_inverse_map(handles, anchors, 96, 96)
    assert map_x.shape == (96, 96)
    # output pixel (x1, y1) = (40, 36) reads the input at (x0, y0) = (30, 30)
    assert map_x[36, 40] == pytest.approx(30.0, abs=1e-3)
    assert map_y[36, 40] == pytest.approx(30.0, abs=1e-3)
    for x, y in [(82, 82), (0, 0), (95, 0), (0, 95), (95, 95)]:
        assert (map_x[y, x], map_y[y, x]) == pytest.approx((x, y), abs=1e-3)


def test_warp_moves_the_handle_blob_to_the_target_and_keeps_far_pixels():
    image, alpha = _scene()
    out, new_alpha = targets.warp_target(
        image, alpha, [((30, 30), (40, 36))], anchors=[(82.5, 82.5)], background=WHITE
    )
    cx, cy = _red_centre(out)
    assert abs(cx - 40) <= 1.0 and abs(cy - 36) <= 1.0, (cx, cy)
    assert new_alpha[36, 40] == pytest.approx(1.0, abs=1e-3)
    # the anchored blue object and the image corners stay where they were
    np.testing.assert_allclose(out[81:85, 81:85], image[81:85, 81:85], atol=2e-2)
    np.testing.assert_allclose(new_alpha[81:85, 81:85], 1.0, atol=2e-2)
    np.testing.assert_allclose(out[:3, :3], 1.0, atol=1e-6)
    assert new_alpha[:3, :3].max() < 1e-6
    assert image[29:32, 29:32, 1].max() == 0.0  # the input is untouched


def test_warp_uncovers_background_where_the_object_left():
    image = np.ones((64, 64, 3), np.float32)
    alpha = np.zeros((64, 64), np.float32)
    image[14:19, 14:19] = (1.0, 0.0, 0.0)  # a lone red 5x5 object centred at (16, 16)
    alpha[14:19, 14:19] = 1.0
    out, new_alpha = targets.warp_target(image, alpha, [((16, 16), (40, 36))])
    cx, cy = _red_centre(out)
    assert abs(cx - 40) <= 1.5 and abs(cy - 36) <= 1.5, (cx, cy)
    assert new_alpha[16, 16] < 0.05 and np.allclose(out[16, 16], 1.0, atol=0.05)
    assert new_alpha[36, 40] > 0.95


def test_warp_rejects_points_outside_and_duplicates():
    image, alpha = _scene(64)
    with pytest.raises(SineError, match="outside the 64x64 image"):
        targets.warp_target(image, alpha, [((10, 10), (70, 10))])
    with pytest.raises(SineError, match="same place"):
        targets.warp_target(image, alpha, [((10, 10), (20, 20))], anchors=[(20, 20)])


# ---- scale / stretch ----------------------------------------------------------------------
def _squares():
    """80x80 white; red 20x20 square rows/cols 20..39 (centre 29.5); blue 10x10 at 60..69."""
    image = np.ones((80, 80, 3), np.float32)
    alpha = np.zeros((80, 80), np.float32)
    image[20:40, 20:40] = (1.0, 0.0, 0.0)
    image[60:70, 60:70] = (0.0, 0.0, 1.0)
    alpha[20:40, 20:40] = alpha[60:70, 60:70] = 1.0
    region = np.zeros((80, 80), bool)
    region[18:42, 18:42] = True  # painted a bit sloppily around the red square
    return image, alpha, region


def _bbox(mask):
    ys, xs = np.nonzero(mask)
    return xs.min(), xs.max(), ys.min(), ys.max()


def test_scale_region_grows_the_part_about_its_centre_and_keeps_the_rest():
    image, alpha, region = _squares()
    out, new_alpha = targets.scale_region(image, alpha, region, 1.5)
    # the part's pixel footprint [19.5, 39.5] about 29.5 becomes [14.5, 44.5]: 30x30 = 900 px
    red = new_alpha.copy()
    red[55:, 55:] = 0
    assert abs(red.sum() - 900) < 20, red.sum()
    assert _bbox(new_alpha[:50, :50] >= 0.5) == (15, 44, 15, 44)
    # the blue square is bit-identical (not covered), and so is the empty background
    assert np.array_equal(out[55:, 55:], image[55:, 55:])
    assert np.array_equal(new_alpha[55:, 55:], alpha[55:, 55:])
    assert np.array_equal(out[:5], image[:5])


def test_scale_region_shrinking_uncovers_background():
    image, alpha, region = _squares()
    out, new_alpha = targets.scale_region(image, alpha, region, 0.5)
    # footprint [19.5, 39.5] -> [24.5, 34.5]: 10x10 = 100 px, pixel (21, 21) left empty
    assert abs(new_alpha[:50, :50].sum() - 100) < 5
    assert new_alpha[21, 21] == 0.0 and np.allclose(out[21, 21], 1.0)
    assert np.allclose(out[29, 29], (1.0, 0.0, 0.0), atol=1e-5)


def test_scale_region_with_a_wrong_size_region_names_both_sizes():
    image, alpha, _ = _squares()
    with pytest.raises(SineError, match="40x30 but the image is 80x80"):
        targets.scale_region(image, alpha, np.ones((30, 40), bool), 1.2)


def test_stretch_axis_scales_the_bounding_box_width_by_the_factor():
    image = np.ones((80, 100, 3), np.float32)
    alpha = np.zeros((80, 100), np.float32)
    image[30:50, 20:40] = (0.2, 0.6, 0.2)  # 20 wide, 20 high
    alpha[30:50, 20:40] = 1.0
    out, new_alpha = targets.stretch_axis(image, alpha, "x", 1.5)
    x0, x1, y0, y1 = _bbox(new_alpha >= 0.5)
    assert (x1 - x0 + 1, y1 - y0 + 1) == (30, 20)  # 20 * 1.5 wide, height unchanged
    assert (x0 + x1) / 2 == pytest.approx(29.5)  # about the centre
    # --about: the left edge stays put
    _, new_alpha = targets.stretch_axis(image, alpha, "x", 1.5, about=19.5)
    assert _bbox(new_alpha >= 0.5)[:2] == (20, 49)
    # along y, with the factor below 1
    _, new_alpha = targets.stretch_axis(image, alpha, "y", 0.5)
    x0, x1, y0, y1 = _bbox(new_alpha >= 0.5)
    assert (x1 - x0 + 1, y1 - y0 + 1) == (20, 10)
    with pytest.raises(SineError, match="x or y"):
        targets.stretch_axis(image, alpha, "z", 1.5)


# ---- texture ------------------------------------------------------------------------------
def test_recolor_rotates_hue_inside_only():
    rng = np.random.default_rng(0)
    image = rng.random((32, 40, 3)).astype(np.float32)
    region = np.zeros((32, 40), bool)
    region[5:15, 10:30] = True
    image[8, 12] = (0.8, 0.4, 0.2)  # H = 20 deg, S = 0.75, V = 0.8
    out = targets.recolor_region(image, region, 120)
    assert np.array_equal(out[~region], image[~region])
    # H = 140 deg, same S and V: (min, max, min + (140 - 120) / 60 * (max - min))
    np.testing.assert_allclose(out[8, 12], (0.2, 0.8, 0.4), atol=1e-4)
    assert not np.allclose(out[region], image[region], atol=1e-3)
    # saturation x0.5: S = 0.375, min = V (1 - S) = 0.5 -> (0.5, 0.8, 0.5 + 1/3 * 0.3)
    out = targets.recolor_region(image, region, 120, saturation=0.5)
    np.testing.assert_allclose(out[8, 12], (0.5, 0.8, 0.6), atol=1e-4)
    assert np.array_equal(out[~region], image[~region])


def test_paint_keeps_shading_and_touches_only_the_region():
    image = np.full((20, 20, 3), 0.3, np.float32)
    image[:, 10:] = 0.9
    region = np.zeros((20, 20), bool)
    region[5:15, 5:15] = True
    image[5:15, 5:10] = 0.25  # two grey halves inside: luminance 0.25 and 0.5, mean 0.375
    image[5:15, 10:15] = 0.5
    out = targets.paint_region(image, region, (0.6, 0.3, 0.0))
    np.testing.assert_allclose(out[7, 7], (0.4, 0.2, 0.0), atol=1e-5)  # gain 0.25 / 0.375
    np.testing.assert_allclose(out[7, 12], (0.8, 0.4, 0.0), atol=1e-5)  # gain 0.5 / 0.375
    assert np.array_equal(out[~region], image[~region])
    flat = targets.paint_region(image, region, (0.6, 0.3, 0.0), shading=False)
    np.testing.assert_allclose(flat[region], np.tile([0.6, 0.3, 0.0], (100, 1)), atol=1e-7)


def test_before_after_and_rgba_round_trip(tmp_path):
    before = np.zeros((10, 12, 3), np.float32)
    after = np.ones((8, 12, 3), np.float32)
    side = targets.before_after(before, after, separator=3)
    assert side.shape == (10, 27, 3)
    assert np.array_equal(side[:, :12], before) and np.array_equal(side[:8, 15:], after)
    assert np.allclose(side[:, 12:15], 0.25)
    alpha = np.linspace(0, 1, 120, dtype=np.float32).reshape(10, 12)
    targets.write_rgba(tmp_path / "a.png", np.full((10, 12, 3), 0.5, np.float32), alpha)
    rgb, a = read_image_rgba(tmp_path / "a.png")
    np.testing.assert_allclose(a, alpha, atol=1 / 255)
    np.testing.assert_allclose(rgb, 128 / 255, atol=1e-6)
    # a composite over white (object colour 0.2) is stored as straight colour 0.2
    composite = np.repeat(0.2 * alpha[..., None] + (1 - alpha[..., None]), 3, axis=2)
    targets.write_rgba(tmp_path / "b.png", composite, alpha, background=WHITE)
    rgb, a = read_image_rgba(tmp_path / "b.png")
    on = a > 0
    np.testing.assert_allclose(rgb[on], 0.2, atol=1.5 / 255)
    np.testing.assert_allclose(rgb[~on], 1.0, atol=1e-6)
    np.testing.assert_allclose(rgb * a[..., None] + (1 - a[..., None]), composite, atol=2 / 255)


# ---- parsing ------------------------------------------------------------------------------
def test_parsing_and_its_errors():
    assert parse_warp("10,20>30,40; 1.5,2>3,4;") == [((10, 20), (30, 40)), ((1.5, 2), (3, 4))]
    assert parse_points("1,2;3,4") == [(1, 2), (3, 4)]
    np.testing.assert_allclose(parse_color("255,0,51"), (1.0, 0.0, 0.2))
    with pytest.raises(SineError, match="x0,y0>x1,y1"):
        parse_warp("10,20-30,40")
    with pytest.raises(SineError, match="e.g. --warp"):
        parse_warp("10,20>30")
    with pytest.raises(SineError, match="as a number"):
        parse_warp("a,20>30,40")
    with pytest.raises(SineError, match="R,G,B"):
        parse_color("1,2")
    with pytest.raises(SineError, match="0..255"):
        parse_color("300,0,0")


# ---- the commands on a tiny fitted run ----------------------------------------------------
@pytest.fixture(scope="module")
def run_root(tmp_path_factory):
    return tiny_feature_run(tmp_path_factory, features=False)


def _stem(run_root, view):
    from recon.rundir import RunDir

    return RunDir(run_root).load_cameras().frames[view].name.rsplit(".", 1)[0]


def test_snapshot_renders_the_view_with_its_opacity(run_root, tmp_path, capsys):
    out = tmp_path / "view.png"
    assert (
        main(["snapshot", str(run_root), "--view", "2", "--out", str(out), "--threads", "1"]) == 0
    )
    assert str(out) in capsys.readouterr().out
    rgb, alpha = read_image_rgba(out)
    assert rgb.shape == (64, 64, 3) and alpha is not None
    mask = read_mask(run_root / "masks" / f"{_stem(run_root, 2)}.png")
    got = alpha >= 0.5
    assert (got & mask).sum() / (got | mask).sum() > 0.8  # the rendered silhouette fits the mask
    # the capture, with its mask as alpha
    out = tmp_path / "capture.png"
    assert (
        main(
            ["snapshot", str(run_root), "--view", "2", "--out", str(out)] + ["--source", "capture"]
        )
        == 0
    )
    rgb, alpha = read_image_rgba(out)
    assert np.array_equal(alpha >= 0.5, mask)
    image = read_image(run_root / "images" / f"{_stem(run_root, 2)}.png")
    assert np.array_equal(rgb, image)


def test_snapshot_view_out_of_range_lists_the_valid_range(run_root, tmp_path, capsys):
    assert main(["snapshot", str(run_root), "--view", "8", "--out", str(tmp_path / "v.png")]) == 2
    assert "valid views are 0..7" in capsys.readouterr().err


def test_target_warp_on_the_rendering(run_root, tmp_path, capsys):
    out = tmp_path / "target.png"
    snap = tmp_path / "view.png"
    main(["snapshot", str(run_root), "--view", "1", "--out", str(snap), "--threads", "1"])
    _, before = read_image_rgba(snap)
    x0, x1, y0, y1 = _bbox(before >= 0.5)
    top = (round((x0 + x1) / 2), y0 + 2)  # a point just inside the object's top edge
    warp = f"{top[0]},{top[1]}>{top[0]},{top[1] - 8}"
    anchor = f"{top[0]},{y1}"  # the bottom stays put
    args = ["target", str(run_root), "--view", "1", "--out", str(out), "--warp", warp]
    args += ["--anchor", anchor]
    assert main(args + ["--threads", "1"]) == 0
    printed = capsys.readouterr().out
    side = tmp_path / "target_before_after.png"
    assert str(out) in printed and str(side) in printed and "render" in printed
    rgb, alpha = read_image_rgba(out)
    assert rgb.shape == (64, 64, 3)
    assert _bbox(alpha >= 0.5)[2] <= y0 - 6  # the top edge moved up ~8 px
    assert abs(_bbox(alpha >= 0.5)[3] - y1) <= 1  # the bottom stayed
    assert read_image(side).shape == (64, 2 * 64 + 4, 3)


def test_target_recolor_on_the_capture_changes_only_the_region(run_root, tmp_path, capsys):
    stem = _stem(run_root, 3)
    region = read_label_map(run_root / "labels" / f"{stem}.png") == 1  # the car's body
    write_mask(tmp_path / "painted.png", region)
    out = tmp_path / "t.png"
    args = ["target", str(run_root), "--view", "3", "--out", str(out), "--source", "capture"]
    assert (
        main(args + ["--recolor", "--region", str(tmp_path / "painted.png"), "--hue", "120"]) == 0
    )
    rgb, alpha = read_image_rgba(out)
    image = read_image(run_root / "images" / f"{stem}.png")
    mask = read_mask(run_root / "masks" / f"{stem}.png")
    assert np.array_equal(rgb[~region], image[~region])
    assert np.array_equal(alpha >= 0.5, mask)
    assert np.abs(rgb[region & mask] - image[region & mask]).max() > 0.1
    capsys.readouterr()
    # paint: the same contract
    args_paint = ["--paint", str(tmp_path / "painted.png"), "--color", "30,200,30"]
    assert main(args + args_paint) == 0
    rgb, _ = read_image_rgba(out)
    assert np.array_equal(rgb[~region], image[~region])
    green = rgb[region & mask]
    assert (green[:, 1] >= green[:, 0]).mean() > 0.9


def test_target_errors_are_one_line_with_the_right_syntax(run_root, tmp_path, capsys):
    base = ["target", str(run_root), "--view", "0", "--out", str(tmp_path / "t.png")]
    base += ["--source", "capture"]
    assert main(base) == 2
    assert "choose exactly one" in capsys.readouterr().err
    assert main(base + ["--warp", "1,2>3,4", "--stretch-axis", "x", "--factor", "2"]) == 2
    assert "several operations" in capsys.readouterr().err
    assert main(base + ["--warp", "1,2,3,4"]) == 2
    assert 'e.g. --warp "' in capsys.readouterr().err
    assert main(base + ["--warp", "1,2>3,4", "--hue", "30"]) == 2
    assert "--hue belongs to --recolor" in capsys.readouterr().err
    write_mask(tmp_path / "small.png", np.ones((32, 48), bool))
    assert main(base + ["--region", str(tmp_path / "small.png"), "--scale", "1.3"]) == 2
    assert "is 48x32 but the view is 64x64" in capsys.readouterr().err
