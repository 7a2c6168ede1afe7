"""Selecting the object of a capture in a room by a box in one view (recon/object_select.py):
the box's checks, and (slow) `sine recon --object-box` on a synthetic turntable whose backdrop
is a cluttered room, scored against the ground-truth masks."""

import json

import numpy as np
import pytest

from recon.object_select import _view_index, check_box, select_masks
from render.errors import SineError

VIEWS = [
    {"name": "r_000.png", "source": "/cap/images/IMG_1.jpg", "width": 64, "height": 48},
    {"name": "r_001.png", "source": "/cap/images/IMG_2.jpg", "width": 64, "height": 48},
]


@pytest.mark.parametrize(
    "box, message",
    [
        ((10, 10, 5, 20), "X1 > X0 and Y1 > Y0"),
        ((70, 10, 90, 20), "lies outside view v (64x48 pixels)"),
        ((-30, -30, -1, -1), "lies outside view v"),
        ((10, 10, 12, 40), "is 2x30 pixels inside view v"),
    ],
)
def test_a_box_outside_the_view_or_too_small_is_refused(box, message):
    with pytest.raises(SineError) as err:
        check_box(box, 64, 48, "v")
    assert message in str(err.value)


def test_a_box_partly_outside_is_clipped_to_the_view():
    assert check_box((-5.5, 3.2, 70, 40.1), 64, 48, "v") == (0, 3, 64, 41)


def test_the_boxed_view_by_index_run_name_or_file_name():
    assert _view_index(VIEWS, "1") == 1
    assert _view_index(VIEWS, "r_001.png") == 1
    assert _view_index(VIEWS, "IMG_1.jpg") == 0
    for view in ("2", "IMG_9.jpg"):
        with pytest.raises(SineError, match="the capture has 2 views, 0 to 1"):
            _view_index(VIEWS, view)


def test_a_box_needs_the_captures_cameras():
    with pytest.raises(SineError, match="use a capture with poses"):
        select_masks(None, VIEWS, None, "0", [1, 2, 30, 40])


@pytest.mark.slow
def test_recon_selects_the_boxed_object_in_a_cluttered_room(tmp_path):
    import sine_cli
    from recon.rundir import RunDir
    from render.io import read_mask

    capture, run = tmp_path / "capture", tmp_path / "run"
    argv = ["synth", "--out", str(capture), "--procedural", "toycar", "--views", "12"]
    argv += ["--width", "64", "--height", "64", "--background", "clutter", "--quiet"]
    assert sine_cli.main(argv) == 0
    gt = {p.name: read_mask(p) for p in sorted((capture / "masks").glob("*.png"))}
    ys, xs = np.nonzero(gt["r_001.png"])
    box = [str(v) for v in (xs.min() - 2, ys.min() - 2, xs.max() + 3, ys.max() + 3)]
    argv = ["recon", str(capture), "--out", str(run), "--object-view", "r_001.png"]
    assert sine_cli.main([*argv, "--object-box", *box]) == 0
    ious = []
    for name, truth in gt.items():
        mask = read_mask(RunDir(run).mask_path(name))
        ious.append((mask & truth).sum() / (mask | truth).sum())
    # the box's cone alone covers about three times the object; the selection finds it
    assert np.mean(ious) >= 0.75 and min(ious) >= 0.6, ious
    state = json.loads((run / "recon_state.json").read_text())["stages"]["masks"]
    assert state["masks_selected"] == 12 and state["object_view"] == "r_001.png"


@pytest.mark.slow
def test_a_box_on_the_room_alone_selects_nothing(tmp_path):
    from recon.object_select import select_object
    from recon.synth import SynthConfig, synthesize
    from render.cameras import load_cameras
    from render.io import read_image

    capture = tmp_path / "capture"
    synthesize(
        SynthConfig(
            out=capture, procedural="toycar", views=12, width=64, height=64, background=["clutter"]
        ),
        progress=False,
    )
    cameras = load_cameras(capture / "cameras.json").frames
    images = [read_image(capture / "images" / c.name) for c in cameras]
    with pytest.raises(SineError, match="the other views do not agree on the object"):
        select_object(cameras, images, 1, (0, 0, 14, 14), progress=False)
