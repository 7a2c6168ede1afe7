"""Template fitting on a tiny self-made run directory: loss goes down, outputs, exact resume."""

import math
import shutil
from dataclasses import replace

import numpy as np
import open3d as o3d
import pytest
import torch

from recon.fit import fit_template, load_template
from recon.fit_config import FitConfig, resolve_preset
from recon.fit_data import pixel_axes, subpixel_dirs
from recon.fit_proxy import make_sampler
from recon.rundir import RunDir
from render.cameras import Camera, CameraSet, look_at
from render.errors import SineError
from render.io import read_image, read_json, read_mask, read_yaml, write_image, write_mask
from render.renderer import render_image
from render.sh import sh_encode
from render.template_field import TemplateField


def _make_run(root, n_views=12, size=48):
    """A sphere (radius 0.5) coloured by its normal, white background, ring of cameras."""
    mesh = o3d.geometry.TriangleMesh.create_sphere(0.5, 40)
    run = RunDir(root)
    run.root.mkdir(parents=True, exist_ok=True)
    o3d.io.write_triangle_mesh(str(run.proxy_mesh), mesh)
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(o3d.t.geometry.TriangleMesh.from_legacy(mesh))
    frames = []
    for i in range(n_views):
        a = 2 * np.pi * i / n_views
        eye = np.array([2.5 * np.cos(a), 2.5 * np.sin(a), 0.8])
        cam = Camera(
            size,
            size,
            50.0,
            50.0,
            size / 2,
            size / 2,
            look_at(eye, np.zeros(3)),
            name=f"v{i}.png",
            split="test" if i % 3 == 0 else "train",
        )
        # each pixel averages 3 x 3 rays, as a camera integrates its area; the mask is the
        # centre ray's hit (as `sine synth` makes them)
        o, d = cam.resized(3 * size, 3 * size).rays()
        t = scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1)))["t_hit"].numpy()
        hit = np.isfinite(t)
        p = o + d * np.where(hit, t, 0)[:, None]
        n = p / np.linalg.norm(p, axis=1, keepdims=True)
        fine = np.where(hit[:, None], 0.5 + 0.4 * n, 1.0).reshape(size, 3, size, 3, 3)
        write_image(run.image_path(cam.name), fine.mean(axis=(1, 3)).astype(np.float32))
        write_mask(run.mask_path(cam.name), hit.reshape(size, 3, size, 3)[:, 1, :, 1])
        frames.append(cam)
    run.save_cameras(CameraSet(frames))
    return run


TINY = dict(
    batch_rays=256,
    log2_table=12,
    max_resolution=64,
    band_samples=8,
    density_hidden=128,  # the width these tiny fits' expectations were measured with
    coarse_samples=2,
    log_every=5,
    checkpoint_every=5,
    previews=1,
    seed=3,
    threads=1,
    lr_mlp=1e-2,
    detail_steps=6,
    detail_batch_rays=128,
    detail_check=0.0,  # the check's own test turns it on
)


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    return _make_run(tmp_path_factory.mktemp("fit") / "run")


def _copy(run, dst):
    shutil.copytree(run.root, dst)
    return RunDir(dst)


def test_fit_reaches_a_psnr_floor_and_writes_outputs(tiny_run, tmp_path):
    run = _copy(tiny_run, tmp_path / "run")
    metrics = fit_template(run.root, FitConfig(iterations=200, **TINY), progress=False)
    log = read_json(run.template / "log.json")
    assert log[0]["step"] == 1 and log[-1]["loss"] < 0.3 * log[0]["loss"]
    assert metrics["iterations"] == 200 and metrics["heldout_views"] == 4
    # Measured 26.9 dB on the 4 held-out views (20.0 on the object's pixels); the sphere's
    # mean colour inside the true mask over the true background scores 21.8 dB, a fit that
    # learnt nothing far less.
    assert read_json(run.template / "metrics.json")["heldout_psnr"] > 25.0
    assert metrics["background_color"] == [1.0, 1.0, 1.0]  # from the masks
    previews = list((run.template / "previews").glob("*.png"))
    assert len(previews) == 1
    assert read_yaml(run.config)["stages"][-1]["stage"] == "fit"
    field, bg = load_template(run.root)
    out = field(torch.zeros(4, 3), torch.tensor([[0.0, 0.0, 1.0]] * 4))
    assert out["rgb"].shape == (4, 3) and out["geo_feat"].shape[0] == 4
    # a re-run with the same settings is a no-op returning the same metrics
    again = fit_template(run.root, FitConfig(iterations=200, **TINY), progress=False)
    assert again["heldout_psnr"] == metrics["heldout_psnr"] and again["skipped"]
    assert torch.load(run.template / "field.pt", weights_only=True)["fit_config"]


def test_resume_gives_the_same_parameters(tiny_run, tmp_path, capsys):
    cfg = FitConfig(iterations=10, **TINY)
    straight = _copy(tiny_run, tmp_path / "a")
    fit_template(straight.root, cfg, progress=False)
    resumed = _copy(tiny_run, tmp_path / "b")
    assert fit_template(resumed.root, cfg, progress=False, stop_at=5) == {"step": 5}
    assert not (resumed.template / "field.pt").exists()
    # then stopped in the colour-detail phase (steps 11-16), whose cache is built again
    assert fit_template(resumed.root, cfg, progress=False, stop_at=13) == {"step": 13}
    fit_template(resumed.root, cfg, progress=False)
    a = torch.load(straight.template / "checkpoint.pt", weights_only=True)
    b = torch.load(resumed.template / "checkpoint.pt", weights_only=True)
    assert a["step"] == b["step"] == 16
    for k, v in a["state"]["field"]["state_dict"].items():
        torch.testing.assert_close(b["state"]["field"]["state_dict"][k], v, rtol=0, atol=0)
    # other options: the finished fit is redone (and says which options changed)
    capsys.readouterr()
    other = fit_template(
        resumed.root, FitConfig(iterations=10, **{**TINY, "seed": 4}), progress=False
    )
    assert "seed: 3 -> 4" in capsys.readouterr().out and not other.get("skipped")
    # what it is made from: the same options on a run whose recon changed a mask fit again
    cfg4 = FitConfig(iterations=10, **{**TINY, "seed": 4})
    assert fit_template(resumed.root, cfg4, progress=False)["skipped"]
    mask = sorted(resumed.masks.glob("*.png"))[0]
    changed = read_mask(mask)
    changed[0, 0] = not changed[0, 0]
    write_mask(mask, changed)
    assert fit_template(resumed.root, cfg4, progress=False, stop_at=1) == {"step": 1}
    assert "masks is not the one it was made from" in capsys.readouterr().out


def test_options_are_checked_before_any_work(tiny_run, tmp_path, capsys):
    from sine_cli import main

    run = _copy(tiny_run, tmp_path / "v")
    assert main(["fit", str(run.root), "--iterations", "-5", "--force", "--quiet"]) == 2
    assert "--iterations must be >= 1 (got -5)" in capsys.readouterr().err
    with pytest.raises(SineError, match="--iterations must be >= 1"):
        fit_template(run.root, FitConfig(iterations=-5, **TINY), progress=False)
    with pytest.raises(SineError, match="--lr-final-factor must be <= 1"):
        fit_template(run.root, FitConfig(lr_final_factor=2.0, **TINY), progress=False)
    assert not run.template.exists() and not (run.root / "template.partial").exists()


def test_force_keeps_the_old_results_until_the_new_fit_finishes(tiny_run, tmp_path):
    run = _copy(tiny_run, tmp_path / "f")
    cfg = FitConfig(iterations=6, **TINY)
    first = fit_template(run.root, cfg, progress=False)
    assert fit_template(run.root, cfg, force=True, progress=False, stop_at=3) == {"step": 3}
    assert read_json(run.template / "metrics.json") == first  # still the old results
    assert (run.template / "field.pt").is_file()
    fit_template(run.root, cfg, force=True, progress=False)
    assert not (run.root / "template.partial").exists()


def test_cli_says_already_done_for_a_finished_fit(tiny_run, tmp_path, capsys):
    from sine_cli import main

    run = _copy(tiny_run, tmp_path / "cli")
    args = ["fit", str(run.root), "--quiet", "--iterations", "3", "--batch-rays", "256"]
    args += ["--log2-table", "12", "--max-resolution", "64", "--previews", "0"]
    args += ["--detail-steps", "2", "--detail-batch-rays", "64"]
    assert main(args) == 0
    assert "fit: 3 steps + 2 colour-detail steps in" in capsys.readouterr().out
    assert main(args + ["--device", "cpu"]) == 0  # a runtime option: still done
    assert "fit: already done with these options (3 steps" in capsys.readouterr().out


def test_missing_proxy_mesh_says_run_recon(tiny_run, tmp_path):
    run = _copy(tiny_run, tmp_path / "c")
    run.proxy_mesh.unlink()
    with pytest.raises(SineError, match="sine recon"):
        fit_template(run.root, FitConfig(iterations=1, **TINY), progress=False)


def test_object_metrics_on_hand_made_images():
    from render.metrics import masked_psnr, masked_ssim, psnr

    gt = np.full((32, 32, 3), 0.5, np.float32)
    mask = np.zeros((32, 32), bool)
    mask[:, :16] = True
    pred = gt.copy()
    pred[mask] += 0.1  # error 0.1 on the object, none on the background
    assert masked_psnr(pred, gt, mask) == pytest.approx(20.0, abs=1e-4)  # 10 log10(1 / 0.01)
    assert psnr(pred, gt) == pytest.approx(10 * np.log10(1 / 0.005), abs=1e-4)  # half the pixels
    assert masked_ssim(gt, gt, mask) == pytest.approx(1.0)
    wrong_background = gt.copy()
    wrong_background[~mask] = 0.0  # columns >= 16 change
    far = np.zeros_like(mask)
    far[:, :6] = True  # beyond SSIM's 7 px window from column 16: unchanged
    assert masked_ssim(wrong_background, gt, far) == pytest.approx(1.0)
    assert masked_ssim(wrong_background, gt, mask) < 0.95


def test_subpixel_rays_hit_the_sub_pixel_centres():
    """2 x 2 sub-pixel rays project to the pixel centre +-0.25 px, u fastest, pixel by pixel:
    the ray layout `render_image(..., supersample=2)` box-filters."""
    cam = Camera(40, 30, 55.0, 60.0, 21.0, 14.5, look_at(np.array([2.0, -1.0, 1.5]), np.zeros(3)))
    centres = cam.pixel_grid()[:5]  # [5, 2]
    origins, dirs = cam.rays(centres)
    axes = torch.as_tensor(pixel_axes(cam), dtype=torch.float32).expand(len(dirs), 3, 3)
    sub = subpixel_dirs(torch.from_numpy(dirs), axes, 2).numpy()  # [20, 3]
    np.testing.assert_allclose(np.linalg.norm(sub, axis=1), 1.0, atol=1e-6)
    pixels, _ = cam.project(np.repeat(origins, 4, axis=0) + 2.0 * sub)
    expected = np.repeat(centres, 4, axis=0) + np.tile(
        [[-0.25, -0.25], [0.25, -0.25], [-0.25, 0.25], [0.25, 0.25]], (5, 1)
    )
    np.testing.assert_allclose(pixels, expected, atol=1e-3)
    one = subpixel_dirs(torch.from_numpy(dirs), axes, 1).numpy()
    np.testing.assert_allclose(one, dirs, atol=1e-6)


def test_ray_selector_draws_in_proportion_to_the_last_errors():
    from recon.fit_data import RayPool, RaySelector

    n = 1000
    pool = RayPool(
        *([None] * 8), errors=torch.full((n,), 1e-4), view=None, edge=None, pixel_axes=None
    )
    pool.errors[7] = 1.0  # one ray still wrong: ~0.9 of the error draws
    selector = RaySelector(pool, 0.5, torch.Generator().manual_seed(0))
    idx = selector.draw(2000)
    assert idx.shape == (2000,) and int(idx.max()) < n
    uniform, by_error = idx[:1000], idx[1000:]
    assert (uniform == 7).sum() < 10  # 1 expected
    assert 850 < int((by_error == 7).sum()) < 950  # 1000 * 1 / (1 + 999e-4) = 909 expected
    selector.record(torch.tensor([7]), torch.tensor([0.0]))
    assert pool.errors[7] == 1e-6  # fixed: back to a floor, no longer drawn
    assert (RaySelector(pool, 0.0, torch.Generator().manual_seed(0)).draw(50) < n).all()


def test_presets_fill_only_the_options_not_given():
    from recon.fit_config import PRESETS, resolve_preset

    assert PRESETS["fast"]["iterations"] < PRESETS["default"]["iterations"]
    assert PRESETS["default"]["iterations"] < PRESETS["quality"]["iterations"]
    fast = resolve_preset(FitConfig(preset="fast"))
    assert (fast.iterations, fast.batch_rays) == (300, 1024)
    default = resolve_preset(FitConfig())
    assert (default.iterations, default.batch_rays) == (1500, 2048)
    assert (fast.detail_steps, default.detail_steps) == (300, 1500)
    assert resolve_preset(FitConfig(detail_steps=0)).detail_steps == 0
    mixed = resolve_preset(FitConfig(preset="quality", iterations=7))
    assert (mixed.iterations, mixed.batch_rays, mixed.log2_table) == (7, 4096, 19)
    # the cheaper step for fast and default, the wider and denser one for quality
    assert (default.density_hidden, default.band_samples) == (64, 12)
    assert (mixed.density_hidden, mixed.band_samples) == (128, 16)
    given = resolve_preset(FitConfig(density_hidden=32, band_samples=20))
    assert (given.density_hidden, given.band_samples) == (32, 20)
    with pytest.raises(SineError, match="--preset"):
        resolve_preset(FitConfig(preset="slow"))


def test_max_resolution_matches_one_cell_to_a_pixel_at_the_object(tmp_path):
    """A camera 4 units from the object's centre with a focal length of 400 px sees 0.01 units
    per pixel there: over [-1, 1] that is 200 cells. The median over the training views counts
    (a held-out view closer in does not), an explicit value wins, no cameras -> 512."""
    from recon.fit_config import FALLBACK_MAX_RESOLUTION, pixel_resolution, resolve_preset

    def cam(distance, focal, split="train"):
        pose = look_at([distance, 0.0, 0.0], [0.0, 0.0, 0.0])
        return Camera(64, 64, focal, focal, 32, 32, pose, split=split)

    assert pixel_resolution([cam(4.0, 400.0)]) == 200
    assert pixel_resolution([cam(4.0, 400.0)], bound=1.5) == 300
    assert pixel_resolution([cam(4.0, 400.0), cam(2.0, 400.0), cam(4.0, 400.0)]) == 200

    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    assert resolve_preset(FitConfig(), run).max_resolution == FALLBACK_MAX_RESOLUTION
    run.save_cameras(CameraSet([cam(4.0, 400.0), cam(3.0, 300.0), cam(1.0, 400.0, "test")]))
    assert resolve_preset(FitConfig(), run).max_resolution == 200
    assert resolve_preset(FitConfig(max_resolution=64), run).max_resolution == 64


def test_refine_proxy_mid_fit_replaces_the_band_and_resumes_exactly(tmp_path):
    """A proxy 20 % too large is refined from the field after 30 % and again after 60 % of
    the steps (accuracy: tests/test_proxy_refine.py, on analytic fields): the template keeps
    the refined proxy (closer to the true sphere of radius 0.5), later stages find it, and a
    fit interrupted between the two refinements resumes to the same parameters (the band's
    width by proxy vertex too: the recon's visual hull meets the proxy at the equator)."""
    import open3d as o3d

    from recon.fit_proxy import template_proxy

    base = _make_run(tmp_path / "base")
    big = o3d.geometry.TriangleMesh.create_sphere(0.6, 40)
    o3d.io.write_triangle_mesh(str(base.proxy_mesh), big)
    hull = np.asarray(big.vertices) * [1.0, 1.0, 1.1]  # the proxy on it at the equator only
    np.savez(base.root / "visual_hull.npz", vertices=hull, faces=big.triangles, voxel=0.02)
    cfg = FitConfig(
        iterations=60, refine_proxy=0.3, refine_rounds=2, refine_views=6, **{**TINY, "lr_mlp": 2e-2}
    )
    straight = _copy(base, tmp_path / "a")
    metrics = fit_template(straight.root, cfg, progress=False)
    refined = metrics["proxy_refined"]
    assert refined["refined"] and refined["rounds"] == 2
    ious = refined["silhouette_iou_rounds"]  # the proxy's before round 1, after each round
    assert len(ious) == 3 and ious[1] > ious[0] and ious[2] > ious[0]
    assert (ious[1], ious[2]) == (refined["silhouette_iou_before"], refined["silhouette_iou_after"])
    assert template_proxy(straight) == straight.template / "proxy_mesh.ply"
    radii = np.linalg.norm(
        np.asarray(o3d.io.read_triangle_mesh(str(template_proxy(straight))).vertices), axis=1
    )
    assert np.median(radii) < 0.59  # closer to the truth (24 tiny steps: a soft field)
    resumed = _copy(base, tmp_path / "b")
    assert fit_template(resumed.root, cfg, progress=False, stop_at=30) == {"step": 30}
    assert fit_template(resumed.root, cfg, progress=False)["proxy_refined"]["rounds"] == 2
    a = torch.load(straight.template / "checkpoint.pt", weights_only=True)
    b = torch.load(resumed.template / "checkpoint.pt", weights_only=True)
    for k, v in a["state"]["field"]["state_dict"].items():
        torch.testing.assert_close(b["state"]["field"]["state_dict"][k], v, rtol=0, atol=0)


def test_refinement_steps_every_fraction_of_the_fit_and_the_rounds_done():
    """Refinements every --refine-proxy of the steps, --refine-rounds times, inside the fit."""
    from recon.fit_proxy import refinement_steps, refinements_done

    assert refinement_steps(FitConfig(iterations=1500, refine_proxy=0.3, refine_rounds=1)) == [450]
    two = FitConfig(iterations=1500, refine_proxy=0.3, refine_rounds=2)
    assert refinement_steps(two) == [450, 900]
    assert refinement_steps(FitConfig(iterations=1500, refine_proxy=0.0, refine_rounds=2)) == []
    # rounds at / after the last step or at step 0 (a short fit) are left out
    assert refinement_steps(FitConfig(iterations=100, refine_proxy=0.5, refine_rounds=2)) == [50]
    assert refinement_steps(FitConfig(iterations=2, refine_proxy=0.2, refine_rounds=4)) == [1]
    assert refinements_done(None) == 0
    assert refinements_done({"refined": True, "rounds": 2}) == 2


def test_the_band_narrows_by_one_factor_per_refinement_round(tmp_path):
    """Before the first refinement the band is --band-width-start wide, after the last
    --band-width, a constant factor between rounds; without refinement it is --band-width.
    By default it starts 3 x wider when the proxy is refined, 1 x on dataset depth."""
    from recon.fit_config import START_BAND, resolve_preset
    from recon.fit_proxy import band_widths
    from render.io import write_json

    four = FitConfig(iterations=1500, refine_proxy=0.2, refine_rounds=4, band_width_start=0.12)
    factor = (1 / 3) ** (1 / 4)
    assert band_widths(four) == pytest.approx([0.12 * factor**k for k in range(5)])
    assert band_widths(four)[-1] == pytest.approx(0.04)
    once = FitConfig(iterations=100, refine_proxy=0.5, refine_rounds=1, band_width_start=0.2)
    assert band_widths(once) == pytest.approx([0.2, 0.04])
    assert band_widths(FitConfig(refine_proxy=0.0, band_width_start=0.2)) == [0.04]
    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    write_json(run.recon_report, {"depth_source": "visual_hull+stereo"})
    assert resolve_preset(FitConfig(), run).band_width_start == pytest.approx(START_BAND * 0.04)
    assert resolve_preset(FitConfig(band_width_start=0.05), run).band_width_start == 0.05
    assert resolve_preset(FitConfig(refine_proxy=0.0), run).band_width_start == 0.04
    write_json(run.recon_report, {"depth_source": "dataset"})
    assert resolve_preset(FitConfig(), run).band_width_start == 0.04


def test_the_start_band_is_wide_only_where_the_recon_had_the_visual_hull_alone(tmp_path):
    """Per proxy vertex, the share of the views seeing it whose recon depth was the hull's
    (not replaced by stereo) sets its start band: --band-width-start at 1, --band-width at
    0, linear between; each vertex narrows geometrically round by round; one width without
    the hull."""
    from recon.depth import HullMesh, bounded_depths
    from recon.fit_proxy import band_at_round
    from recon.proxy_band import stereo_pixels, unmeasured_share
    from render.io import write_depth

    run = RunDir(tmp_path / "run")
    run.depth.mkdir(parents=True)
    sphere = o3d.geometry.TriangleMesh.create_sphere(0.6, 60)
    vertices, faces = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    np.savez(
        run.root / "visual_hull.npz",
        vertices=vertices,
        faces=faces,
        voxel=0.02,
        open_faces=np.zeros(len(faces), bool),
    )
    hull = HullMesh(vertices, faces, 0.02, np.zeros(len(faces), bool))
    cams = []
    for i in range(4):  # at azimuths 0, 90, 180, 270 degrees
        a = np.pi / 2 * i
        eye = np.array([3.0 * np.cos(a), 3.0 * np.sin(a), 0.0])
        cams.append(Camera(64, 64, 60.0, 60.0, 32, 32, look_at(eye, np.zeros(3)), name=f"v{i}.png"))
    run.save_cameras(CameraSet(cams))
    for i, (cam, z) in enumerate(zip(cams, bounded_depths(hull, cams), strict=True)):
        measured = i < 2  # views 0 and 1: stereo moved every pixel; 2 and 3: the hull's
        write_depth(run.depth_path(cam.name), np.where(z > 0, z + 0.05, 0) if measured else z)
    stereo = stereo_pixels(run)
    share = unmeasured_share(stereo, vertices, faces)
    # equator vertices seen by views 0 + 1 (azimuth 45), 1 + 2 (135), 2 + 3 (225)
    azimuth = np.degrees(np.arctan2(vertices[:, 1], vertices[:, 0])) % 360
    equator = np.abs(vertices[:, 2]) < 0.05
    for centre, expected in ((45, 0.0), (135, 0.5), (225, 1.0)):
        near = equator & (np.abs(azimuth - centre) < 10)
        assert near.any() and share[near] == pytest.approx(expected)
    cfg = FitConfig(iterations=1000, refine_proxy=0.2, refine_rounds=4, band_width_start=0.12)
    start = 0.04 + 0.08 * share
    assert band_at_round(cfg, stereo, (vertices, faces), 0) == pytest.approx(start)
    halfway = band_at_round(cfg, stereo, (vertices, faces), 2)
    assert halfway == pytest.approx(0.04 * (start / 0.04) ** 0.5)
    assert band_at_round(cfg, stereo, (vertices, faces), 4) == 0.04
    (run.root / "visual_hull.npz").unlink()
    assert stereo_pixels(run) is None
    assert band_at_round(cfg, None, (vertices, faces), 0) == pytest.approx(0.12)


def test_capture_background_composites_rays_outside_the_masks_over_their_own_pixels(tmp_path):
    """A backdrop of random colours (no single colour explains it): with --background capture
    the rays outside the masks are composited over their own pixels, so the field learns no
    fog in front of the backdrop and the object fits far better than with one learned colour."""
    run = _copy(_make_run(tmp_path / "base"), tmp_path / "run")
    rng = np.random.default_rng(0)
    for cam in run.load_cameras().frames:
        image = read_image(run.image_path(cam.name))
        mask = read_mask(run.mask_path(cam.name))
        image[~mask] = rng.uniform(0, 1, (int((~mask).sum()), 3))
        write_image(run.image_path(cam.name), image)
    fogs, objects = {}, {}
    for mode in ("learn", "capture"):
        # the main fit's background handling alone (the colour-detail phase off)
        options = {**TINY, "detail_steps": 0}
        cfg = FitConfig(iterations=150, background=mode, mask_weight=0.0, **options)
        metrics = fit_template(run.root, cfg, progress=False, force=True)
        assert metrics["background_behind_rays"] == ("capture" if mode == "capture" else "colour")
        field, bg = load_template(run.root)
        cam = run.load_cameras().frames[1]
        out = render_image(cam, field, make_sampler(FitConfig(**TINY), run), bg)
        outside = ~read_mask(run.mask_path(cam.name))
        fogs[mode] = float(out["opacity"][outside].mean())
        objects[mode] = metrics["heldout_psnr_object"]
    # measured: fog 0.014 -> 0.003, object PSNR 17.7 -> 23.2 dB
    assert fogs["capture"] < 0.5 * fogs["learn"]
    assert objects["capture"] > objects["learn"] + 3.0


def test_capture_background_without_masks_is_a_clear_error(tmp_path):
    run = _copy(_make_run(tmp_path / "base"), tmp_path / "run")
    shutil.rmtree(run.root / "masks")
    cfg = FitConfig(iterations=5, background="capture", **TINY)
    with pytest.raises(SineError, match="has no masks"):
        fit_template(run.root, cfg, progress=False)


def test_the_proxy_is_refined_by_default_only_when_it_was_estimated(tmp_path):
    """Hull + stereo proxies are refined every 20 % of the steps, four times; proxies from
    the dataset's depth or an unknown source are not; an explicit fraction refines once."""
    from recon.fit_config import DEFAULT_REFINE_AT, DEFAULT_REFINE_ROUNDS, resolve_preset
    from recon.fit_proxy import refinement_steps
    from render.io import write_json

    def refine(cfg: FitConfig) -> tuple[float, int]:
        resolved = resolve_preset(cfg, run)
        return resolved.refine_proxy, resolved.refine_rounds

    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    assert refine(FitConfig()) == (0.0, 1)  # no report: nothing known
    estimated = (DEFAULT_REFINE_AT, DEFAULT_REFINE_ROUNDS)
    for source, expected in (("dataset", (0.0, 1)), ("visual_hull+stereo", estimated)):
        write_json(run.recon_report, {"depth_source": source})
        assert refine(FitConfig()) == expected
    assert refinement_steps(resolve_preset(FitConfig(), run)) == [300, 600, 900, 1200]
    assert refine(FitConfig(refine_proxy=0.5)) == (0.5, 1)  # an explicit fraction: once
    assert refine(FitConfig(refine_proxy=0.0)) == (0.0, 1)
    assert refine(FitConfig(refine_rounds=2)) == (DEFAULT_REFINE_AT, 2)


def test_the_masks_edge_is_box_filtered_by_default_only_when_the_capture_brought_its_masks(
    tmp_path,
):
    from recon.fit_config import resolve_preset
    from render.io import write_json

    run = RunDir(tmp_path / "run")
    run.root.mkdir()

    def chosen(cfg: FitConfig) -> int:
        return resolve_preset(cfg, run).train_supersample

    assert chosen(FitConfig()) == 1  # no report: nothing known
    for given, estimated, expected in ((36, 0, 2), (30, 6, 1), (0, 36, 1)):
        write_json(run.recon_report, {"masks_given": given, "masks_automatic": estimated})
        assert chosen(FitConfig()) == expected
    write_json(run.recon_report, {"masks_given": 36, "masks_automatic": 0})
    assert chosen(FitConfig(train_supersample=1)) == 1  # the user's choice stands
    assert chosen(FitConfig(train_supersample=3)) == 3


def test_silhouette_edge_marks_the_rings_on_both_sides_of_the_boundary():
    from recon.fit_data import silhouette_edge

    mask = np.zeros((7, 8), bool)
    mask[2:5, 3:6] = True  # a 3 x 3 square
    edge = silhouette_edge(mask)
    ring = np.zeros((7, 8), bool)
    ring[1:6, 2:7] = True  # the square grown by one pixel ...
    ring[3, 4] = False  # ... without its only pixel whose neighbours are all inside
    assert (edge == ring).all()
    assert not silhouette_edge(np.ones((4, 4))).any()


def test_box_filter_on_silhouette_pixels_only(tiny_run, tmp_path, monkeypatch):
    """--train-supersample 2: only the batch's pixels on the mask's boundary get 2 x 2 rays,
    and the fit learns the sphere."""
    import recon.fit

    boxed, drawn = [], []
    real_draw = recon.fit.RaySelector.draw

    def draw(self, n):
        idx = real_draw(self, n)
        drawn.append(int(self.pool.edge[idx].sum()))
        return idx

    def counted(dirs, axes, s):
        boxed.append(len(dirs))
        return subpixel_dirs(dirs, axes, s)

    monkeypatch.setattr(recon.fit.RaySelector, "draw", draw)
    monkeypatch.setattr(recon.fit, "subpixel_dirs", counted)
    run = _copy(tiny_run, tmp_path / "run")
    cfg = FitConfig(iterations=200, train_supersample=2, **TINY)
    metrics = fit_template(run.root, cfg, progress=False)
    assert len(boxed) == 200 and boxed == [n for n in drawn if n]
    assert 0 < min(boxed) and max(boxed) < 256  # some pixels of each batch, never all
    # The images average each pixel's area, as the box filter models: measured 24.7 dB on the
    # held-out object pixels (28.8 whole image) against the one-ray fit's 20.0 (26.9), whose
    # silhouette pixels stay hard-edged.
    assert metrics["heldout_psnr_object"] > 22.5 and metrics["heldout_psnr"] > 25.0


def test_the_saved_field_is_the_moving_average_of_the_last_steps(tiny_run, tmp_path):
    """A window of 0.25 of 10 steps: decay d = 1 - 1 / 2.5 = 0.6; field.pt holds a_10 with
    a_5 = w_5 (half-way), a_k = d a_(k-1) + (1 - d) w_k (w_k: the weights after k steps);
    every stop and resume in between keeps the average."""
    decay = 0.6
    options = {**TINY, "detail_steps": 0}  # the main steps' weights (no colour-detail phase)
    cfg = FitConfig(iterations=10, average_window=0.25, **options)
    run = _copy(tiny_run, tmp_path / "run")
    weights = {}
    for k in range(5, 11):
        fit_template(run.root, cfg, progress=False, stop_at=k if k < 10 else None)
        folder = run.template if k == 10 else run.root / "template.partial"
        saved = torch.load(folder / "checkpoint.pt", weights_only=True)
        assert saved["step"] == k
        weights[k] = saved["state"]["field"]["state_dict"]
    expected = dict(weights[5])
    for k in range(6, 11):
        expected = {n: decay * a + (1 - decay) * weights[k][n] for n, a in expected.items()}
    field = torch.load(run.template / "field.pt", weights_only=True)["field"]
    moved = 0
    for name, value in field.items():
        torch.testing.assert_close(value, expected[name], rtol=1e-5, atol=1e-6)
        moved += int(not torch.equal(value, weights[10][name]))
    assert moved > 0  # the average is not the last step's weights
    # without the average, field.pt is the last step's weights
    plain = _copy(tiny_run, tmp_path / "plain")
    fit_template(
        plain.root, FitConfig(iterations=10, average_window=0.0, **options), progress=False
    )
    last = torch.load(plain.template / "checkpoint.pt", weights_only=True)["state"]["field"]
    for name, value in torch.load(plain.template / "field.pt", weights_only=True)["field"].items():
        torch.testing.assert_close(value, last["state_dict"][name], rtol=0, atol=0)


# ---- the colour-detail phase (recon/colour_detail.py) -------------------------------------------
def _detail_field(max_resolution=64):
    from recon.fit_config import field_config

    cfg = FitConfig(iterations=10, **{**TINY, "max_resolution": max_resolution, "detail_steps": 5})
    return TemplateField(field_config(resolve_preset(cfg)))


def test_a_fresh_detail_branch_renders_as_the_field_without_it():
    torch.manual_seed(0)
    with_detail = _detail_field()
    plain = TemplateField(replace(with_detail.cfg, detail=None))
    missing, unexpected = plain.load_state_dict(with_detail.state_dict(), strict=False)
    assert not missing and unexpected and all(k.startswith("detail_") for k in unexpected)
    x = torch.rand(500, 3) * 1.6 - 0.8
    d = torch.nn.functional.normalize(torch.randn(500, 3), dim=-1)
    a, b = with_detail(x, d), plain(x, d)
    torch.testing.assert_close(a["rgb"], b["rgb"], rtol=0, atol=0)
    torch.testing.assert_close(a["sigma"], b["sigma"], rtol=0, atol=0)
    with pytest.raises(ValueError, match="needs the points"):
        with_detail.color(a["geo_feat"], d)


def test_the_detail_cache_renders_the_training_rays_as_the_field_does(tiny_run, tmp_path):
    """The cached samples' composite is the rendered colour (up to the samples left out, each
    below MIN_WEIGHT), the detail steps lower the loss and train only the detail branch."""
    from recon.colour_detail import (
        CHECK_EVERY,
        MIN_WEIGHT,
        build_detail_cache,
        check_psnr,
        check_views,
        detail_rays,
        detail_step,
        reset_branch,
    )
    from recon.colour_detail import composite as detail_composite
    from recon.fit_data import build_ray_pool, load_views
    from render.renderer import render_rays

    run = _copy(tiny_run, tmp_path / "d")
    cfg = FitConfig(iterations=60, **{**TINY, "detail_steps": 0})
    fit_template(run.root, cfg, progress=False)
    fitted, bg = load_template(run.root)
    field = TemplateField(replace(fitted.cfg, detail=_detail_field().cfg.detail))
    field.load_state_dict(fitted.state_dict(), strict=False)
    torch.nn.init.normal_(field.detail_net[-1].weight, std=0.5)  # a branch that does something
    sampler = make_sampler(resolve_preset(cfg, run), run)
    pool = build_ray_pool(load_views(run, "train"), sampler, torch.device("cpu"))
    rays = detail_rays(pool, False, torch.Generator().manual_seed(0))
    assert len(rays) == len(pool.origins)
    behind = bg().expand(len(rays), 3)
    with torch.no_grad():
        cache = build_detail_cache(field, sampler, pool, rays, behind, chunk=1000)
        rendered = render_rays(field, pool.origins, pool.dirs, sampler, bg(), hits=pool.hits)
    assert len(cache) <= len(cache.points) <= len(cache) * sampler.samples_per_ray
    owner = torch.repeat_interleave(torch.arange(len(cache)), cache.count)
    sh = sh_encode(cache.dirs[owner], field.cfg.sh_degree)
    with torch.no_grad():
        rgb = torch.sigmoid(cache.base_logits + field.detail_logits(cache.points, sh))
    colour = torch.zeros(len(cache), 3).index_add(0, owner, cache.weights[:, None] * rgb)
    composite = colour + (1 - cache.opacity[:, None]) * cache.behind
    gap = (composite - rendered["rgb"]).abs().max().item()
    assert gap <= 10 * MIN_WEIGHT  # the samples below MIN_WEIGHT, nothing else
    everything = torch.arange(len(cache))
    with torch.no_grad():
        torch.testing.assert_close(detail_composite(field, cache, everything), composite)
    # the check's PSNR without / with the branch; with a zeroed branch the two agree
    without, with_branch = check_psnr(field, cache, everything, chunk=777)
    error = ((composite - cache.target) ** 2).mean()
    assert with_branch == pytest.approx(-10 * math.log10(error.item()), abs=1e-4)
    held = check_views(pool.view[rays], int(pool.view.max()) + 1)
    views = pool.view[rays][held].unique().tolist()
    assert views == list(range(CHECK_EVERY // 2, int(pool.view.max()) + 1, CHECK_EVERY))
    j = int(torch.nonzero(held)[0, 0])  # drawn among one ray: the loss is that ray's error
    with torch.no_grad():
        one = detail_step(field, cache, 8, torch.Generator(), among=torch.tensor([j]))["rgb"]
    assert one.item() == pytest.approx(((composite[j] - cache.target[j]) ** 2).mean().item())
    reset_branch(field)
    assert check_psnr(field, cache, everything)[1] == pytest.approx(without, abs=1e-5)
    torch.nn.init.normal_(field.detail_net[-1].weight, std=0.5)
    # edge pixels out when the fit box-filters them
    assert len(detail_rays(pool, True, torch.Generator())) == int((~pool.edge).sum())

    for p in field.parameters():
        p.requires_grad_(False)
    detail_params = [*field.detail_grid.parameters(), *field.detail_net.parameters()]
    for p in detail_params:
        p.requires_grad_(True)
    opt = torch.optim.Adam(detail_params, lr=1e-2)
    generator = torch.Generator().manual_seed(0)
    full = detail_step(field, cache, len(cache), generator)["rgb"].item()
    for _ in range(60):
        opt.zero_grad()
        detail_step(field, cache, 256, generator)["rgb"].backward()
        opt.step()
    assert detail_step(field, cache, len(cache), generator)["rgb"].item() < 0.7 * full
    assert all(p.grad is None for p in field.color_net.parameters())


def test_the_detail_check_keeps_or_drops_the_branch_and_resumes_exactly(
    tiny_run, tmp_path, monkeypatch
):
    """--detail-check: the first steps leave every 6th training view out; the verdict (the
    branch kept only if it renders those views' rays better) is recorded and survives a stop
    on either side of it; a dropped branch renders as none (its last layer zero)."""
    cfg = FitConfig(iterations=10, **{**TINY, "detail_steps": 8, "detail_check": 0.5})
    straight = _copy(tiny_run, tmp_path / "a")
    metrics = fit_template(straight.root, cfg, progress=False)
    without, with_branch = metrics["detail_check_psnr_without"], metrics["detail_check_psnr_with"]
    assert metrics["detail_kept"] == (with_branch > without)
    field, _ = load_template(straight.root)
    last = field.detail_net[-1].weight
    assert bool((last == 0).all()) != metrics["detail_kept"]
    resumed = _copy(tiny_run, tmp_path / "b")
    assert fit_template(resumed.root, cfg, progress=False, stop_at=12) == {"step": 12}
    again = fit_template(resumed.root, cfg, progress=False)
    assert again["detail_check_psnr_with"] == with_branch
    a = torch.load(straight.template / "field.pt", weights_only=True)["field"]
    b = torch.load(resumed.template / "field.pt", weights_only=True)["field"]
    for k, v in a.items():
        torch.testing.assert_close(b[k], v, rtol=0, atol=0)
    # a verdict against the branch: zeroed, the rest of the phase not run
    monkeypatch.setattr("recon.colour_detail.check_psnr", lambda *args, **kw: (30.0, 20.0))
    dropped = _copy(tiny_run, tmp_path / "c")
    metrics = fit_template(dropped.root, cfg, progress=False)
    assert metrics["detail_kept"] is False and metrics["detail_steps_taken"] == 4
    field, _ = load_template(dropped.root)
    assert not field.detail_net[-1].weight.any() and not field.detail_net[-1].bias.any()
    assert torch.load(dropped.template / "checkpoint.pt", weights_only=True)["step"] == 18


def test_ray_pool_casts_only_the_proxy_window(tiny_run):
    """The pool cast through each view's pixel window of the inflated proxy is the pool of
    casting every pixel, tensor for tensor."""
    from recon.fit_data import build_ray_pool, load_views

    class EveryPixel:  # the same sampler without `pixel_window`
        def __init__(self, sampler):
            self.cast = sampler.cast

    sampler = make_sampler(resolve_preset(FitConfig(**TINY), tiny_run), tiny_run)
    views = load_views(tiny_run, "train")
    cam = views[0][0]
    row0, row1, col0, col1 = sampler.pixel_window(cam)
    assert (row1 - row0) * (col1 - col0) < cam.width * cam.height  # something is culled
    windowed = build_ray_pool(views, sampler, torch.device("cpu"))
    every = build_ray_pool(views, EveryPixel(sampler), torch.device("cpu"))
    assert windowed.n_total == every.n_total and len(windowed.origins) > 0
    for name in ("origins", "dirs", "rgb", "mask", "miss_rgb", "view", "edge", "pixel_axes"):
        assert torch.equal(getattr(windowed, name), getattr(every, name)), name
    for name in ("t_hit", "t_inflated", "near", "far", "t_exit"):
        assert torch.equal(getattr(windowed.hits, name), getattr(every.hits, name)), name
