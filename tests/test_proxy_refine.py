"""The proxy refine loop: a bad proxy re-fused from a field's rendered depth (analytic fields)."""

from __future__ import annotations

import numpy as np
import open3d as o3d
import pytest
import torch
from scene_helpers import ring, sphere_depths, sphere_masks

from recon.proxy_mesh import ProxyParams, closing_depths, fuse_tsdf, tsdf_voxel, write_mesh
from recon.proxy_refine import (
    RefineConfig,
    ray_depths,
    refine_proxy,
    refine_run,
    render_depth,
    run_proxy_params,
    silhouette_ious,
    view_subset,
)
from recon.rundir import RunDir
from render.cameras import CameraSet
from render.io import write_json, write_mask
from render.raycast import mesh_arrays
from render.sampler import BandSampler, ProxyRaycaster, UniformSampler

R = 0.5  # the true sphere's radius


class SphereField(torch.nn.Module):
    """Density: a ball of radius R (a sharp sigmoid step); colour by direction."""

    def forward(self, x, d):
        r = x.norm(dim=-1)
        inside = torch.sigmoid((R - r) / 0.001)
        rgb = (0.5 + 0.4 * x / r.clamp_min(1e-6)[:, None]).clamp(0, 1)
        return {"sigma": 1000.0 * inside, "rgb": rgb}


def cameras(size: int = 96):
    """16 views: 8 from 30 degrees above the equator, 8 from 30 below (2.6 from the origin)."""
    up, _ = ring(8, (0, 0, 0), (0, 0, 1), radius=2.25, height=1.3, w=size, h=size)
    down, _ = ring(8, (0, 0, 0), (0, 0, 1), radius=2.25, height=-1.3, w=size, h=size)
    f = 1.15 * size
    return [c.replace(fx=f, fy=f, name=f"v{i:02d}.png") for i, c in enumerate(up + down)]


def ellipsoid(axes=(0.62, 0.55, 0.45)):
    mesh = o3d.geometry.TriangleMesh.create_sphere(1.0, 30)
    mesh.vertices = o3d.utility.Vector3dVector(np.asarray(mesh.vertices) * np.array(axes))
    return mesh


def radial_error(mesh) -> np.ndarray:
    return np.abs(np.linalg.norm(np.asarray(mesh.vertices), axis=1) - R)


def test_view_subset_is_evenly_spaced():
    assert view_subset(10, 0) == list(range(10)) and view_subset(3, 5) == [0, 1, 2]
    assert view_subset(9, 3) == [0, 4, 8]


def test_ray_depths_of_a_half_space_of_constant_density():
    """Density 10 for x > 0, a ray along +x from x = -2: the unit sphere spans t in [1, 3], the
    opacity accumulated by t is 1 - exp(-10 (t - 2)), so it reaches 0.5 at 2 + ln 2 / 10 and
    0.2 at 2 + ln 1.25 / 10; the expected distance is 2 + 1/10 (the tail beyond t = 3 weighs
    e^-10)."""

    def field(x, d):
        return {"sigma": torch.where(x[:, 0] > 0, 10.0, 0.0), "rgb": torch.zeros_like(x)}

    origins = torch.tensor([[-2.0, 0.0, 0.0], [-2.0, 5.0, 0.0]])  # the second misses
    dirs = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    sampler = UniformSampler(n_coarse=256, n_importance=0)
    for level, expected in ((0.5, 2 + np.log(2) / 10), (0.2, 2 + np.log(1.25) / 10)):
        out = ray_depths(field, sampler, origins, dirs, level)
        assert out["level"][0].item() == pytest.approx(expected, abs=2e-3)
        assert out["opacity"][0].item() == pytest.approx(1.0, abs=1e-4)
        assert out["expected"][0].item() == pytest.approx(2.1, abs=4e-3)
        assert out["level"][1].item() == float("inf") and out["opacity"][1].item() == 0.0
    half = ray_depths(lambda x, d: {"sigma": 0.1 * field(x, d)["sigma"]}, sampler, origins, dirs)
    assert half["opacity"][0].item() == pytest.approx(1 - np.exp(-1.0), abs=1e-3)
    assert half["level"][0].item() == pytest.approx(2 + np.log(2), abs=2e-3)


def test_bad_proxy_moves_onto_the_field_surface():
    """An ellipsoid proxy (semi-axes 0.62, 0.55, 0.45 around a ball of radius 0.5): its
    vertices lie 0.046 from the sphere on average (0.12 at the long axis' ends); the field's
    depth, rendered through a band wide enough to hold the ball (+-0.15 around the proxy),
    re-fused at the proxy stage's settings (voxel: 1.5 pixel footprints = 1.5 * 2.6 / 110 =
    0.035), gives a proxy within half a voxel (0.018) of the sphere on average."""
    cams = cameras()
    masks = sphere_masks(cams, np.zeros(3), R)
    bad = ellipsoid()
    assert radial_error(bad).mean() == pytest.approx(0.046, abs=0.002)
    sampler = BandSampler(ProxyRaycaster(bad, inflate=0.15), n_band=32, n_coarse=4)
    mesh, stats = refine_proxy(
        SphereField(), sampler, cams, masks, ProxyParams(), bad, RefineConfig(1.0)
    )
    assert radial_error(mesh).mean() < 0.018
    assert np.percentile(radial_error(mesh), 95) < 0.035  # one voxel
    assert stats["refine_voxel_size"] == pytest.approx(1.5 * 2.6 / 110, rel=0.01)
    # the ellipsoid's silhouettes cover 0.84 of the union with the masks; the new ones > 0.93
    assert stats["silhouette_iou_before"] == pytest.approx(0.84, abs=0.02)
    assert stats["silhouette_iou_after"] > 0.93
    assert stats["silhouette_iou_after"] == pytest.approx(
        np.mean(silhouette_ious(mesh, cams, masks))
    )
    assert stats["proxy_closed_after"] and stats["proxy_triangles_before"] == 3480
    # how far the field's surface lay from the proxy: the median |shift| is a few hundredths
    assert 0.02 < stats["refine_shift_median"] < 0.12


def test_depth_rendered_on_chosen_pixels_is_the_full_render_there():
    """`render_depth(pixels=)` (what a masked refinement renders: the dilated mask) gives the
    full image's values on those pixels, opacity 0 and distance inf elsewhere."""
    cam = cameras(32)[0]
    sampler = BandSampler(ProxyRaycaster(ellipsoid(), inflate=0.15), n_band=32, n_coarse=4)
    cfg = RefineConfig(refine_chunk=100)  # several chunks
    full = render_depth(SphereField(), sampler, cam, cfg)
    chosen = np.zeros((32, 32), bool)
    chosen[5:20, 8:30] = True
    part = render_depth(SphereField(), sampler, cam, cfg, pixels=chosen)
    assert np.isfinite(full[1][chosen]).sum() > 100  # the ball is in the chosen box
    for whole, some in zip(full, part, strict=True):
        np.testing.assert_allclose(some[chosen], whole[chosen], rtol=1e-5, atol=1e-6)
    assert (part[0][~chosen] == 0).all() and np.isinf(part[1][~chosen]).all()


def test_a_known_silhouette_iou_is_not_cast_again():
    """`old_ious` (the last round's `silhouette_ious_after`) stands for the old proxy's."""
    cams = cameras(48)
    masks = sphere_masks(cams, np.zeros(3), R)
    bad = ellipsoid()
    sampler = BandSampler(ProxyRaycaster(bad, inflate=0.15), n_band=32, n_coarse=4)
    cfg = RefineConfig(refine_views=4)
    _, cast = refine_proxy(SphereField(), sampler, cams, masks, ProxyParams(), bad, cfg)
    known = [0.5] * len(cams)
    _, given = refine_proxy(
        SphereField(), sampler, cams, masks, ProxyParams(), bad, cfg, old_ious=known
    )
    assert cast["silhouette_iou_before"] == pytest.approx(0.84, abs=0.03)
    assert given["silhouette_iou_before"] == 0.5
    assert len(cast["silhouette_ious_after"]) == len(cams)
    assert np.mean(cast["silhouette_ious_after"]) == cast["silhouette_iou_after"]


def test_half_scale_and_a_subset_of_views_still_refine():
    """8 of the 16 views at half size (48 px): the voxel doubles (0.071) and the bound with it."""
    cams = cameras()
    masks = sphere_masks(cams, np.zeros(3), R)
    bad = ellipsoid()
    sampler = BandSampler(ProxyRaycaster(bad, inflate=0.15), n_band=32, n_coarse=4)
    cfg = RefineConfig(refine_scale=0.5, refine_views=8)
    mesh, stats = refine_proxy(SphereField(), sampler, cams, masks, ProxyParams(), bad, cfg)
    assert stats["refine_views"] == 8
    assert stats["refine_voxel_size"] == pytest.approx(1.5 * 2.6 / 55, rel=0.01)
    assert radial_error(mesh).mean() < 0.036 < radial_error(bad).mean()
    assert stats["silhouette_iou_after"] > stats["silhouette_iou_before"] + 0.05


def test_carving_erases_a_closing_surface_in_front_of_the_real_depth():
    """Real depth of a ball of radius 0.3 (np.inf off its silhouette: seen empty), closed by a
    sphere of radius 0.6 seen from the closing views. The shell lies 0.3 in front of the real
    surface, beyond the TSDF band (3 voxels of 1.5 * 2.6 / 110 = 0.035: 0.106) and, near the
    poles, outside every ring view's cone of the ball: without carving it stays; with carving
    only the ball remains (within a voxel)."""
    cams = cameras()
    depths = sphere_depths(cams, np.zeros(3), 0.3)
    seen_empty = [np.where(d > 0, d, np.inf).astype(np.float32) for d in depths]
    closing = closing_depths(*mesh_arrays(o3d.geometry.TriangleMesh.create_sphere(0.6, 40)))
    radii = {}
    for carve in (True, False):
        mesh = fuse_tsdf(cams, seen_empty, 1 / 64, 3.0, closing=closing, carve=carve)
        radii[carve] = np.linalg.norm(np.asarray(mesh.vertices), axis=1)
    assert np.abs(radii[True] - 0.3).max() < tsdf_voxel(cams, 1 / 64) == pytest.approx(0.035, 0.01)
    assert (radii[False] > 0.55).sum() > 100


def test_refine_run_uses_the_training_views_masks_and_the_runs_proxy_settings(tmp_path):
    """A run directory: 16 views (every 4th held out), masks, the ellipsoid as proxy_mesh.ply
    and recon_state.json asking for 2000 triangles: 12 views are rendered, the proxy settings
    are the run's, the proxy file is left alone."""
    cams = [c.replace(split="test" if i % 4 == 0 else "train") for i, c in enumerate(cameras())]
    run = RunDir(tmp_path / "run")
    run.root.mkdir()
    for cam, mask in zip(cams, sphere_masks(cams, np.zeros(3), R), strict=True):
        write_mask(run.mask_path(cam.name), mask)
    run.save_cameras(CameraSet(cams))
    write_mesh(run.proxy_mesh, ellipsoid())
    write_json(
        run.root / "recon_state.json", {"options": {"proxy_mesh": {"target_triangles": 2000}}}
    )
    assert run_proxy_params(run).target_triangles == 2000
    assert run_proxy_params(run).voxel_size == ProxyParams().voxel_size
    sampler = BandSampler(ProxyRaycaster(ellipsoid(), inflate=0.15), n_band=32, n_coarse=4)
    mesh, stats = refine_run(run, SphereField(), sampler)
    assert stats["refine_views"] == 12 and len(mesh.triangles) <= 2000
    assert radial_error(mesh).mean() < 0.018
    assert stats["silhouette_iou_after"] > stats["silhouette_iou_before"] + 0.08
    assert len(o3d.io.read_triangle_mesh(str(run.proxy_mesh)).triangles) == 3480


class TwoBallField(torch.nn.Module):
    """SphereField's ball and a small one beside it (radius 0.05, centre 0.68 from the origin:
    0.13 apart), a part of the object that touches nothing."""

    small_centre = torch.tensor([0.0, 0.0, 0.68])

    def forward(self, x, d):
        out = SphereField()(x, d)
        small = torch.sigmoid((0.05 - (x - self.small_centre).norm(dim=-1)) / 0.001)
        out["sigma"] = out["sigma"] + 1000.0 * small
        return out


def test_refinement_keeps_a_small_separate_part():
    """A part of ~1 % of the body's triangles, apart from it (as the carving leaves a hand cut
    off at its wrist): the refinement keeps it (--refine-min-component 0.002); recon's 0.02
    would drop it, and its band with it."""
    cams = cameras(128)
    masks = [a | b for a, b in zip(sphere_masks(cams, np.zeros(3), R),
             sphere_masks(cams, np.array([0.0, 0.0, 0.68]), 0.05), strict=True)]  # fmt: skip
    body = o3d.geometry.TriangleMesh.create_sphere(0.52, 30)
    part = o3d.geometry.TriangleMesh.create_sphere(0.07, 12).translate((0.0, 0.0, 0.68))
    old = body + part
    sampler = BandSampler(ProxyRaycaster(old, inflate=0.05), n_band=24, n_coarse=4)

    def parts(min_component):
        mesh, _ = refine_proxy(
            TwoBallField(), sampler, cams, masks, ProxyParams(), old,
            RefineConfig(refine_min_component=min_component), progress=False,
        )  # fmt: skip
        _, counts, _ = mesh.cluster_connected_triangles()
        return sorted(np.asarray(counts).tolist(), reverse=True)

    kept = parts(RefineConfig().refine_min_component)
    assert len(kept) == 2 and 0.002 < kept[1] / kept[0] < 0.02
    assert len(parts(0.02)) == 1
