"""Dataset depth with estimated poses: used (rescaled) only when one scale fits it, else dropped."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scene_helpers import ring, sphere_depths

from recon.poses import SfmResult, depth_scale_to_sfm, fit_depth_scale
from render.cameras import Camera
from render.errors import SineError
from render.io import read_depth, write_depth


def test_fit_depth_scale_hand_computed():
    a = [1.9, 2.0, 2.1, 2.0, 2.0]
    b = [2.0, 2.0, 2.0, 1.98, 2.02]
    fit = fit_depth_scale({"a": a, "b": b}, tolerance=0.025)
    # median of the 10 ratios = 2; deviations 0 (x6), 0.01 (x2), 0.05 (x2): median 0, 8 of 10
    # within 2.5 %; both views' medians are 2.
    assert fit.factor == pytest.approx(2.0)
    assert fit.residual == pytest.approx(0.0) and fit.within == pytest.approx(0.8)
    assert fit.worst_view_offset == pytest.approx(0.0) and fit.consistent()
    # view b at 1.5 x the scale of view a: the median is between them, both views are off
    fit = fit_depth_scale({"a": [2.0] * 6, "b": [3.0] * 5}, tolerance=0.025)
    assert fit.factor == pytest.approx(2.0)  # 6 of 11 ratios are 2
    assert fit.residual == 0.0 and fit.worst_view == "b"
    assert fit.worst_view_offset == pytest.approx(0.5) and not fit.consistent()
    # a view with fewer than 5 points does not count on its own
    fit = fit_depth_scale({"a": [2.0] * 10, "b": [3.0] * 4}, tolerance=0.025)
    assert fit.worst_view == "a" and fit.consistent()
    # too few points: no factor, not consistent, no numbers in the report
    fit = fit_depth_scale({"a": [2.0] * 9})
    assert fit.factor is None and not fit.consistent()
    assert fit.to_dict()["dataset_depth_scale_residual"] is None


def sfm_scene(scale: float, n: int = 6, w: int = 64, h: int = 48):
    """A sphere (radius 0.6) seen by a ring of cameras; the "SfM" frame is the true frame times
    `scale`. Returns the true cameras, their depth maps and an SfmResult whose observations are
    sphere points seen in every view (SfM units)."""
    cams, _ = ring(n=n, center=np.zeros(3), axis=(0, 0, 1), radius=2.5, height=1.0, w=w, h=h)
    cams = [c.replace(fx=60.0, fy=60.0) for c in cams]
    depths = sphere_depths(cams, np.zeros(3), 0.6)
    observations, sfm_cams = {}, []
    for cam, depth in zip(cams, depths, strict=True):
        rows, cols = np.nonzero(depth > 0)
        pix = np.stack([cols + 0.5, rows + 0.5], 1)[::3]  # [M, 2]
        z = depth[rows, cols][::3]
        origins, dirs = cam.rays(pix)
        pts = origins + dirs * (z / cam.z_per_unit_distance(pix))[:, None]  # [M, 3]
        observations[cam.name] = (pix, scale * pts)
        c2w = cam.camera_to_world.copy()
        c2w[:3, 3] *= scale
        sfm_cams.append(cam.replace(camera_to_world=c2w))
    result = SfmResult(
        cameras=sfm_cams,
        unregistered=[],
        mean_reprojection_error_px=0.1,
        points=np.zeros((0, 3)),
        num_models=1,
        distortion=np.zeros(4),
        observations=observations,
        mapper="incremental",
    )
    return cams, depths, result


def _write(tmp_path, cams: list[Camera], depths) -> dict:
    paths = {}
    for cam, depth in zip(cams, depths, strict=True):
        paths[cam.name] = tmp_path / f"{cam.name}.npy"
        write_depth(paths[cam.name], depth)
    return paths


def test_depth_scale_to_sfm_keeps_consistent_and_flags_inconsistent_depth(tmp_path):
    cams, depths, result = sfm_scene(scale=2.5)
    obs, sfm_cams = result.observations, result.cameras
    fit = depth_scale_to_sfm(obs, _write(tmp_path / "same", cams, depths), sfm_cams)
    # SfM z = 2.5 x the true z at every point (float32 depth: tiny deviations)
    assert fit.factor == pytest.approx(2.5, rel=1e-5) and fit.residual < 1e-5
    assert fit.within == 1.0 and fit.consistent()
    # the same depth in millimetres: still one scale
    mm = _write(tmp_path / "mm", cams, [d * 1000 for d in depths])
    assert depth_scale_to_sfm(obs, mm, sfm_cams).factor == pytest.approx(2.5e-3, rel=1e-5)
    # inverse depth (disparity-like): ratio z^2 spreads with the sphere's relief
    inverse = [np.where(d > 0, 1.0 / np.maximum(d, 1e-6), 0.0) for d in depths]
    fit = depth_scale_to_sfm(obs, _write(tmp_path / "inv", cams, inverse), sfm_cams)
    assert fit.residual > 0.05 and not fit.consistent()
    # every other view in another unit (x 1.3): each view is consistent, the set is not
    per_view = [d * (1.3 if i % 2 else 1.0) for i, d in enumerate(depths)]
    fit = depth_scale_to_sfm(obs, _write(tmp_path / "pv", cams, per_view), sfm_cams)
    assert fit.worst_view_offset > 0.1 and not fit.consistent()
    # garbage: uniform noise where the object is
    rng = np.random.default_rng(0)
    noise = [np.where(d > 0, rng.uniform(0.5, 5.0, d.shape), 0.0) for d in depths]
    fit = depth_scale_to_sfm(obs, _write(tmp_path / "noise", cams, noise), sfm_cams)
    assert fit.residual > 0.2 and not fit.consistent()


def test_consistent_depth_ratios_find_the_scale_from_a_wrong_guess():
    """Poses in units 2.5 x the depth maps' (a sphere off the ring's axis, 12 views 30 degrees
    apart): lifting each view's pixels by the ratio that lands them on a partner's depth finds
    2.5 from a guess 12 % off; a scale per view (every other view's depth x 1.3) shows up as a
    view offset; and a guess beyond the searched span finds nothing to fit."""
    from recon.turntable import consistent_depth_ratios, partner_views

    cams, _ = ring(n=12, center=np.zeros(3), axis=(0, 0, 1), radius=2.5, height=1.0, w=96, h=72)
    cams = [c.replace(fx=90.0, fy=90.0) for c in cams]
    centre = np.array([0.15, -0.1, 0.1])
    depths = sphere_depths(cams, centre, 0.6)
    masks = [d > 0 for d in depths]
    posed = []
    for cam in cams:
        c2w = cam.camera_to_world.copy()
        c2w[:3, 3] *= 2.5
        posed.append(cam.replace(camera_to_world=c2w))
    # ring neighbours are 30 degrees apart: partners are the views one and two steps away
    assert sorted(partner_views(posed, 0)) == [1, 11]
    fit = fit_depth_scale(consistent_depth_ratios(posed, masks, depths, guess=2.2), 0.025)
    assert fit.factor == pytest.approx(2.5, rel=2e-3) and fit.consistent()
    assert fit.points > 12 * 500
    per_view = [d * (1.3 if i % 2 else 1.0) for i, d in enumerate(depths)]
    fit = fit_depth_scale(consistent_depth_ratios(posed, masks, per_view, guess=2.5), 0.025)
    assert not fit.consistent()
    far = consistent_depth_ratios(posed, masks, depths, guess=1.0)
    assert sum(len(v) for v in far.values()) < 100


@pytest.fixture(scope="module")
def small_run(tmp_path_factory):
    """A 6-view 64x48 synthetic capture with depth, ingested (cameras and depth in the run)."""
    from recon import synth
    from recon.ingest import IngestConfig, ingest_capture
    from recon.rundir import RunDir

    root = tmp_path_factory.mktemp("depthcheck")
    synth.synthesize(
        synth.SynthConfig(out=root / "cap", procedural="figurine", views=6, width=64, height=48),
        progress=False,
    )
    run = RunDir(root / "run")
    ingest_capture(root / "cap", run, IngestConfig(width=64))
    return run


def _fake_sfm(run, scale: float) -> SfmResult:
    """SfM of the run's own cameras and depth, its frame scaled by `scale`."""
    cams = run.load_cameras().frames
    observations, sfm_cams = {}, []
    for cam in cams:
        depth = read_depth(run.depth_path(cam.name))
        rows, cols = np.nonzero(depth > 0)
        pix = np.stack([cols + 0.5, rows + 0.5], 1)[::2]
        z = depth[rows, cols][::2]
        origins, dirs = cam.rays(pix)
        pts = origins + dirs * (z / cam.z_per_unit_distance(pix))[:, None]
        observations[cam.name] = (pix, scale * pts)
        c2w = cam.camera_to_world.copy()
        c2w[:3, 3] *= scale
        sfm_cams.append(cam.replace(camera_to_world=c2w))
    return SfmResult(sfm_cams, [], 0.1, np.zeros((0, 3)), 1, np.zeros(4), observations, "global")


def _copy_run(run, dest):
    import shutil

    from recon.rundir import RunDir

    shutil.copytree(run.root, dest)
    return RunDir(dest)


def test_use_sfm_rescales_consistent_depth(small_run, tmp_path):
    from recon.pipeline import Pipeline
    from recon.recon_config import ReconConfig

    run = _copy_run(small_run, tmp_path / "run")
    pipe = Pipeline(run, ReconConfig())
    views = pipe.views()
    before = {r["name"]: read_depth(run.depth_path(r["name"])) for r in views}
    result = _fake_sfm(run, 3.0)
    info = {}
    pipe.use_sfm(views, result, result.cameras, info)
    assert info["dataset_depth_verified"] is True
    assert info["dataset_depth_to_sfm_scale"] == pytest.approx(3.0, rel=1e-4)
    for name, depth in before.items():
        assert np.allclose(read_depth(run.depth_path(name)), 3.0 * depth, rtol=1e-4)


def test_use_sfm_drops_inconsistent_depth_and_the_depth_stage_does_without(
    small_run, tmp_path, capsys
):
    from recon.pipeline import Pipeline
    from recon.recon_config import ReconConfig

    run = _copy_run(small_run, tmp_path / "run")
    cfg = ReconConfig(hull_resolution=32)
    pipe = Pipeline(run, cfg)
    views = pipe.views()
    result = _fake_sfm(run, 3.0)
    for i, r in enumerate(views):  # half of the views' depth in other units
        if i % 2:
            path = run.depth_path(r["name"])
            write_depth(path, read_depth(path) * 1.5)
    before = {r["name"]: read_depth(run.depth_path(r["name"])) for r in views}
    info = {}
    pipe.use_sfm(views, result, result.cameras, info)
    out = capsys.readouterr().out
    assert "WARNING: the capture's depth maps do not agree with the sfm poses" in out
    assert "worst view" in out and "dropped" in out
    assert info["dataset_depth_verified"] is False
    # ratios 3 (even views) and 2 (odd): the median is 2, 2.5 or 3, the worst view >= 20 % off
    assert info["dataset_depth_worst_view_offset"] >= 0.2 - 1e-4
    assert "dataset_depth_to_sfm_scale" not in info
    for name, depth in before.items():  # not rescaled
        assert np.array_equal(read_depth(run.depth_path(name)), depth)
    # the depth stage sees no dataset depth: --depth-method dataset refuses, auto uses the hull
    pipe.state["stages"]["poses"] = {"done": True, **info}
    pipe.cfg = dataclasses.replace(cfg, depth_method="dataset")
    with pytest.raises(SineError, match="depth maps were dropped"):
        pipe.stage_depth()
    pipe.cfg = dataclasses.replace(cfg, depth_method="visual_hull")
    assert pipe.stage_depth()["depth_source"] == "visual_hull"


def test_undistorted_depth_never_mixes_values(tmp_path):
    from recon.poses import undistort_depth_in_place

    cam = Camera(64, 48, 50.0, 50.0, 32.0, 24.0)
    depth = np.zeros((48, 64), np.float32)
    depth[10:38, 12:52] = 2.0
    depth[20:28, 25:40] = 3.0
    path = tmp_path / "d.npy"
    write_depth(path, depth)
    undistort_depth_in_place(path, cam, np.zeros(4))
    assert np.array_equal(read_depth(path), depth)
    undistort_depth_in_place(path, cam, np.array([-0.3, 0.0, 0.0, 0.0]))
    out = read_depth(path)
    assert set(np.unique(out).tolist()) <= {0.0, 2.0, 3.0} and not np.array_equal(out, depth)
    assert out[24, 32] == 3.0  # the centre does not move
