"""`sine masks` on a tiny distilled run: files, errors, and the painted part beats chance."""

from __future__ import annotations

import numpy as np
import pytest
from feature_run_helpers import tiny_feature_run

from edit.feature_maps import FeatureMapRenderer
from edit.part_masks import resolve_view, semantic_masks
from recon.rundir import RunDir
from render.errors import SineError
from render.io import read_json, read_label_map, write_mask
from sine_cli import main


@pytest.fixture(scope="module")
def run_root(tmp_path_factory):
    return tiny_feature_run(tmp_path_factory)


def _labels(root, name):
    return read_label_map(root / "labels" / (name.rsplit(".", 1)[0] + ".png"))


def test_masks_cli_writes_masks_sheet_and_metrics(run_root, tmp_path):
    cams = RunDir(run_root).load_cameras().frames
    region = _labels(run_root, cams[1].name) == 1  # paint the body in view 1
    write_mask(tmp_path / "painted.png", region)
    out = tmp_path / "out"
    rc = main(
        ["masks", str(run_root), "--view", "1", "--region", str(tmp_path / "painted.png")]
        + ["--out", str(out), "--quiet", "--num-samples", "200"]
    )
    assert rc == 0
    masks = sorted(p.name for p in (out / "masks").glob("*.png"))
    assert masks == sorted(c.name.rsplit(".", 1)[0] + ".png" for c in cams)
    import cv2

    m = cv2.imread(str(out / "masks" / masks[1]), cv2.IMREAD_UNCHANGED)
    assert m.shape == (64, 64) and set(np.unique(m)) <= {0, 255} and (m == 255).any()
    sheet = cv2.imread(str(out / "overlay_contact_sheet.png"))
    assert sheet is not None and sheet.shape[1] == 6 * 160
    metrics = read_json(out / "metrics.json")
    assert metrics["edit_view"] == cams[1].name and metrics["views"] == len(cams)
    assert metrics["region_pixels"] == int(region.sum())
    assert metrics["config"]["num_clusters"] == 15 and metrics["config"]["num_samples"] == 200
    assert np.load(out / "semantic_centres.npy").shape == (15, 64)  # centred: PCA coefficients
    assert metrics["rule"] == "contrast" and metrics["config"]["refine"] is True
    assert np.load(out / "semantic_rest_centres.npy").shape == (15, 64)
    centre_points = np.load(out / "semantic_centre_points.npy")  # the spatial term's, run units
    assert centre_points.shape == (15, 3) and np.abs(centre_points).max() < 1.5
    # the part's mask agrees with the GT body in the other views better than chance
    ious = []
    for cam in cams[2:]:
        got = cv2.imread(str(out / "masks" / (cam.name.rsplit(".", 1)[0] + ".png")), 0) > 0
        gt = _labels(run_root, cam.name) == 1
        ious.append((got & gt).sum() / max((got | gt).sum(), 1))
    assert np.mean(ious) > 0.5, ious


def test_wrong_size_empty_or_off_object_region_is_an_error(run_root, tmp_path, capsys):
    write_mask(tmp_path / "small.png", np.ones((32, 48), bool))
    args = ["masks", str(run_root), "--view", "0", "--out", str(tmp_path / "o"), "--quiet"]
    assert main(args + ["--region", str(tmp_path / "small.png")]) == 2
    assert "48x32" in capsys.readouterr().err
    write_mask(tmp_path / "empty.png", np.zeros((64, 64), bool))
    assert main(args + ["--region", str(tmp_path / "empty.png")]) == 2
    assert "empty" in capsys.readouterr().err
    corner = np.zeros((64, 64), bool)
    corner[:3, :3] = True  # background only
    with pytest.raises(SineError, match="does not touch the object"):
        semantic_masks(run_root, 0, corner, tmp_path / "o2", progress=False)
    (tmp_path / "file").write_text("")
    with pytest.raises(SineError, match="--out .* is an existing file"):
        semantic_masks(run_root, 0, corner, tmp_path / "file", progress=False)
    assert not (tmp_path / "o" / "metrics.json").exists()


def test_resolve_view_by_index_name_and_stem(run_root):
    cams = RunDir(run_root).load_cameras().frames
    assert resolve_view(cams, "2")[0] == 2 and resolve_view(cams, -1)[0] == len(cams) - 1
    assert resolve_view(cams, cams[3].name)[0] == 3
    assert resolve_view(cams, cams[3].name.rsplit(".", 1)[0])[0] == 3
    with pytest.raises(SineError, match="out of range"):
        resolve_view(cams, "99")
    with pytest.raises(SineError, match="neither"):
        resolve_view(cams, "nope.png")


def test_painted_part_selected_better_than_chance(run_root, tmp_path):
    """Paint the toycar's cabin in one view: other views' masks overlap the cabin far better than
    marking a random subset of the object of the same size would. (At 64x64 the object spans
    ~6 DINO patches: the body / wheels are not separable at this size, the cabin is.)"""
    cams = RunDir(run_root).load_cameras().frames
    edit = 2
    region = _labels(run_root, cams[edit].name) == 2
    out = tmp_path / "out"
    semantic_masks(run_root, edit, region, out, progress=False)
    gains = []
    for i, cam in enumerate(cams):
        if i == edit:
            continue
        import cv2

        mask = cv2.imread(str(out / "masks" / (cam.name.rsplit(".", 1)[0] + ".png")), 0) > 0
        lab = _labels(run_root, cam.name)
        gt, obj = lab == 2, lab > 0
        iou = (mask & gt).sum() / max((mask | gt).sum(), 1)
        frac = mask[obj].mean() if obj.any() else 0.0
        chance = (frac * gt.sum()) / max(gt.sum() + frac * obj.sum() - frac * gt.sum(), 1)
        gains.append(iou - chance)
    assert np.mean(gains) > 0.15


def test_half_scale_feature_maps_match_full_scale(run_root):
    import torch

    cam = RunDir(run_root).load_cameras().frames[2]
    full, obj_full = FeatureMapRenderer(run_root, render_scale=1.0)(cam)
    half, obj_half = FeatureMapRenderer(run_root, render_scale=0.5)(cam)
    assert half.shape == full.shape == (64, 64, 64) and obj_half.shape == (64, 64)  # [C, H, W]
    both = torch.from_numpy(obj_full & obj_half)
    assert (obj_full != obj_half).mean() < 0.05  # only edge pixels differ
    cos = torch.nn.functional.cosine_similarity(full[:, both], half[:, both], dim=0)
    assert cos.median() > 0.95, cos.median()
    # the surface points: on the camera's rays at the template's depth, and at half scale the
    # same up to the upsampling (opacity-weighted, so silhouette pixels stay on the object)
    _, _, at_full = FeatureMapRenderer(run_root, render_scale=1.0).maps(cam)
    _, _, at_half = FeatureMapRenderer(run_root, render_scale=0.5).maps(cam)
    origins, dirs = cam.rays()  # [H*W, 3]
    flat = at_full.reshape(-1, 3) - origins
    along = (flat * dirs).sum(axis=1, keepdims=True) / (dirs * dirs).sum(axis=1, keepdims=True)
    off_ray = np.linalg.norm(flat - along * dirs, axis=1).reshape(64, 64)
    assert off_ray[obj_full].max() < 1e-4 and (along.reshape(64, 64)[obj_full] > 0).all()
    gap = np.linalg.norm(at_full - at_half, axis=-1)[obj_full & obj_half]
    assert np.median(gap) < 0.02 and np.abs(at_half[obj_half]).max() < 1.5
