"""Self-checks of a reconstruction (recon/selfcheck.py): they stop inconsistent poses and pass
right ones."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scene_helpers import ring, sphere_masks

from recon import synth
from recon.ingest import IngestConfig
from recon.pipeline import run_recon
from recon.recon_config import ReconConfig
from recon.rundir import RunDir
from recon.selfcheck import (
    CheckThresholds,
    check_poses,
    looks_like_turntable,
    require_trusted_poses,
    ring_fit,
    silhouette_consistency,
)
from render.cameras import load_cameras
from render.errors import SineError
from render.io import read_json, read_mask


def _rz(deg: float) -> np.ndarray:
    a = np.radians(deg)
    r = np.eye(4)
    r[:2, :2] = [[np.cos(a), -np.sin(a)], [np.sin(a), np.cos(a)]]
    return r


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    out = tmp_path_factory.mktemp("synth")
    cfg = synth.SynthConfig(out=out, procedural="toycar", views=12, width=96, height=96)
    synth.synthesize(cfg, progress=False)
    return out


def test_ring_fit_of_a_tilted_ring_in_order_and_shuffled():
    cams, axis = ring(n=12, radius=4.0)
    fit = ring_fit(cams)
    assert fit["ring_residual"] < 1e-9 and fit["radius"] == pytest.approx(4.0)
    assert abs(abs(fit["axis"] @ axis) - 1) < 1e-9
    assert np.diff(fit["angles_deg"]) == pytest.approx([30.0] * 11)  # 360 / 12
    assert fit["monotone"] and fit["backward_deg"] == 0.0
    # views 3 and 4 swapped: one step of 30 deg backwards
    swapped = cams[:3] + [cams[4], cams[3]] + cams[5:]
    assert ring_fit(swapped)["backward_deg"] == pytest.approx(30.0)
    # one centre pushed 1 radius outwards: RMS distance to the best circle ~ 1 / sqrt(12) (less:
    # the circle moves towards it)
    moved = [c.replace(camera_to_world=c.camera_to_world.copy()) for c in cams]
    moved[0].camera_to_world[:3, 3] += 4.0 * (moved[0].center - [1.0, 2.0, 3.0]) / 4.27
    assert 0.1 < ring_fit(moved)["ring_residual"] < 0.3


def test_silhouette_consistency_of_a_sphere_is_high_and_falls_with_a_wrong_pose():
    centre, r = np.array([1.0, 2.0, 3.0]), 1.0
    cams, _ = ring(n=8)
    masks = sphere_masks(cams, centre, r)
    ious = silhouette_consistency(cams, masks, width=160, resolution=64)
    assert ious.min() > 0.9
    # camera 0 turned by 15 degrees about its own centre (its image would move by ~40 px, more
    # than the sphere's radius of ~35 px): its mask no longer agrees with the others'
    wrong = list(cams)
    c2w = cams[0].camera_to_world.copy()
    a = np.radians(15.0)
    turn = np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])
    c2w[:3, :3] = c2w[:3, :3] @ turn
    wrong[0] = cams[0].replace(camera_to_world=c2w)
    bad = silhouette_consistency(wrong, masks, width=160, resolution=64)
    # one view may disagree when carving: the wrong view is the one that scores low
    assert bad[0] < ious[0] - 0.1 and bad[1:].min() > 0.9


def test_thin_parts_with_true_cameras_pass(tmp_path):
    """A chair (legs and slats a pixel or two wide at 128 px) seen by its true cameras: the
    carving's one-pixel margin around every thin part does not count as disagreement."""
    cfg = synth.SynthConfig(out=tmp_path, procedural="chair", views=8, width=128, height=128)
    synth.synthesize(cfg, progress=False)
    cams = load_cameras(tmp_path / "cameras.json").frames
    masks = [read_mask(tmp_path / "masks" / c.name) for c in cams]
    ious = silhouette_consistency(cams, masks)
    assert ious.mean() > CheckThresholds().min_silhouette_iou + 0.03


def test_check_poses_passes_true_cameras_and_stops_perturbed_ones(capture):
    cams = load_cameras(capture / "cameras.json").frames
    masks = [read_mask(capture / "masks" / c.name) for c in cams]
    good = check_poses(cams, masks, CheckThresholds(), reprojection_px=0.4, turntable=True)
    assert good.verdict == "ok" and good.reasons == []
    assert good.numbers["hull_iou_mean"] > 0.85 and good.numbers["ring_residual"] < 1e-6
    # every other camera turned 90 degrees further around the object: a ring still, but not
    # monotone (steps of +120 and -60 degrees), and the hull no longer explains the masks (the
    # car's narrow front silhouette now stands where its long side is seen: ~0.6 of its length)
    bad_cams = [
        c.replace(camera_to_world=_rz(90.0) @ c.camera_to_world) if i % 2 else c
        for i, c in enumerate(cams)
    ]
    bad = check_poses(bad_cams, masks, CheckThresholds(), reprojection_px=0.4, turntable=True)
    assert bad.verdict == "poor"
    assert bad.numbers["hull_iou_mean"] < 0.8 and bad.numbers["ring_backward_deg"] == 60.0
    assert any("mean silhouette IoU" in r for r in bad.reasons)
    assert any("not monotone" in r for r in bad.reasons)
    # an absurd reprojection error alone is a reason
    wild = check_poses(cams, masks, CheckThresholds(), reprojection_px=9e151)
    assert wild.verdict == "poor" and "reprojection error is 9e+151 px" in wild.reasons[0]
    assert check_poses(cams, masks, CheckThresholds(), float("nan")).verdict == "poor"


def test_looks_like_turntable(capture):
    cams = load_cameras(capture / "cameras.json").frames
    masks = [read_mask(capture / "masks" / c.name) for c in cams]
    assert looks_like_turntable(masks)
    shuffled = [masks[i] for i in (0, 4, 8, 1, 5, 9, 2, 6, 10, 3, 7, 11)]  # 120 deg apart
    assert not looks_like_turntable(shuffled)
    assert not looks_like_turntable(masks[:5])  # too few views to tell


def _perturbed_capture(capture, out):
    """The capture with every other pose turned 90 degrees further around the object."""
    import shutil

    shutil.copytree(capture, out)
    data = json.loads((out / "transforms.json").read_text())
    for i, frame in enumerate(data["frames"]):
        if i % 2:
            m = np.array(frame["transform_matrix"])
            frame["transform_matrix"] = (_rz(90.0) @ m).tolist()
    (out / "transforms.json").write_text(json.dumps(data))
    return out


def test_recon_stops_on_inconsistent_poses_and_goes_on_when_accepted(capture, tmp_path):
    cap = _perturbed_capture(capture, tmp_path / "cap")
    run = RunDir(tmp_path / "run")
    cfg = ReconConfig(target_triangles=2000, tsdf_voxel_size=1 / 64, hull_resolution=48)
    with pytest.raises(SineError, match=r"self-check after poses failed: .*silhouette IoU 0\.\d+"):
        run_recon(cap, run, cfg, IngestConfig(width=96))
    report = read_json(run.recon_report)
    assert report["verdict"] == "poor" and report["stopped_after"] == "poses"
    assert report["self_check_poses"]["hull_iou_mean"] < 0.8
    assert not run.proxy_mesh.is_file()
    with pytest.raises(SineError, match="self-check found its poses poor"):
        require_trusted_poses(run)  # what `sine fit` asks first
    # the same run again stops again (the poses stage is not redone)
    with pytest.raises(SineError, match="self-check after poses failed"):
        run_recon(None, run, cfg)
    # accepted: the run goes on to the end, the verdict stays poor
    report = run_recon(None, run, ReconConfig(**{**cfg.__dict__, "accept_poor_poses": True}))
    assert report["verdict"] == "poor" and report["poor_accepted"] is True
    assert run.proxy_mesh.is_file()
    require_trusted_poses(run)  # accepted: no error


def test_recon_verdict_ok_on_true_poses(capture, tmp_path):
    run = RunDir(tmp_path / "run")
    cfg = ReconConfig(target_triangles=2000, tsdf_voxel_size=1 / 64, hull_resolution=48)
    report = run_recon(capture, run, cfg, IngestConfig(width=96))
    assert report["verdict"] == "ok" and report["verdict_reasons"] == []
    assert report["self_check_poses"]["hull_iou_mean"] > 0.85
    assert report["self_check_report"]["verdict"] == "ok"
    require_trusted_poses(run)


def test_mask_iou_within_a_pixel_forgives_an_outline_not_a_shift():
    from render.metrics import mask_iou, mask_iou_within

    a = np.zeros((40, 40), bool)
    a[10:20, 10:20] = True  # 100 pixels
    grown = np.zeros_like(a)
    grown[9:21, 9:21] = True  # 144: one pixel all around
    assert mask_iou(a, grown) == pytest.approx(100 / 144)
    assert mask_iou_within(a, grown) == 1.0
    shifted = np.zeros_like(a)
    shifted[10:20, 15:25] = True  # 5 pixels right: 50 shared; 40 of each farther than a pixel
    assert mask_iou_within(a, shifted) == pytest.approx(50 / (50 + 40 + 40))
