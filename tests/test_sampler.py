"""Proxy ray casting, band sampling, uniform + importance sampling, and rendering through them."""

import numpy as np
import open3d as o3d
import pytest
import torch

from render.renderer import render_image, render_rays
from render.sampler import (
    BandSampler,
    ProxyRaycaster,
    UniformSampler,
    sample_pdf,
    sphere_interval,
)


def _plane(z=0.0, size=0.9):
    v = np.array([[-size, -size, z], [size, -size, z], [size, size, z], [-size, size, z]])
    f = np.array([[0, 1, 2], [0, 2, 3]])  # counter-clockwise seen from +z: normal +z
    return v, f


def _sphere(r=0.5):
    m = o3d.geometry.TriangleMesh.create_sphere(r, 60)
    return m


def _rays(xs, z=-3.0, dz=1.0):
    o = torch.tensor([[x, 0.0, z] for x in xs], dtype=torch.float32)
    d = torch.tensor([[0.0, 0.0, dz]] * len(xs), dtype=torch.float32)
    return o, d


def test_sphere_interval():
    o, d = _rays([0.0, 0.6, 2.0], z=-3.0)
    near, far, hit = sphere_interval(o, d, 1.0)
    assert hit.tolist() == [True, True, False]
    torch.testing.assert_close(near[0], torch.tensor(2.0))
    torch.testing.assert_close(far[0], torch.tensor(4.0))
    torch.testing.assert_close(near[1], torch.tensor(3.0 - 0.8))


def test_plane_hit_and_inflated_hit():
    rc = ProxyRaycaster(_plane(), inflate=0.05)
    o = torch.tensor([[0.1, 0.2, 0.5]])
    d = torch.tensor([[0.0, 0.0, -1.0]])
    hits = rc.cast(o, d)
    torch.testing.assert_close(hits.t_hit, torch.tensor([0.5]))
    torch.testing.assert_close(hits.t_inflated, torch.tensor([0.45]))
    assert hits.hit.tolist() == [True]


def test_band_samples_around_sphere_depth_and_misses():
    d_band = 0.05
    sampler = BandSampler(ProxyRaycaster(_sphere(0.5), inflate=d_band), n_band=16, n_coarse=4)
    # centre ray, ray missing the sphere but inside the inflated shell, clear miss
    o, d = _rays([0.0, 0.52, 0.7])
    hits = sampler.cast(o, d)
    assert hits.hit.tolist() == [True, True, False]
    assert np.isfinite(hits.t_hit[0].item()) and not np.isfinite(hits.t_hit[1].item())
    assert abs(hits.t_hit[0].item() - 2.5) < 2e-3  # tessellated sphere
    sub = hits[hits.hit]
    t, delta = sampler.sample(sub, perturb=True, generator=torch.Generator().manual_seed(0))
    assert t.shape == (2, sampler.samples_per_ray) == (2, 21)
    assert torch.all(t[:, 1:] >= t[:, :-1]) and torch.all(delta >= 0)
    # the bins tile the ray-in-sphere interval [2, 4] of the centre ray
    torch.testing.assert_close(delta[0].sum(), torch.tensor(2.0), atol=1e-4, rtol=0)
    in_band = (t[0] > 2.5 - d_band - 2e-3) & (t[0] < 2.5 + d_band + 2e-3)
    assert in_band.sum() >= 16
    # passing ray (0.02 outside the sphere): its band is its stretch inside the inflated
    # sphere (radius 0.55): 2 sqrt(0.55^2 - 0.52^2) = 0.358 long, centred on the closest
    # approach at t = 3 (tessellated spheres: a few mm off)
    lo, hi = sampler.band(sub)
    torch.testing.assert_close(lo[1], sub.t_inflated[1])
    assert abs((hi[1] - lo[1]).item() - 2 * np.sqrt(0.55**2 - 0.52**2)) < 0.02
    assert abs((lo[1] + hi[1]).item() / 2 - 3.0) < 5e-3


def test_band_width_by_vertex():
    # widths 0.02 on the sphere's x < 0 half, 0.08 on x > 0: a ray through each half gets its
    # own band around the hit, and so does a ray passing by the wide side's inflated copy
    mesh = _sphere(0.5)
    x = np.asarray(mesh.vertices)[:, 0]
    widths = np.where(x > 0, 0.08, 0.02)
    sampler = BandSampler(ProxyRaycaster(mesh, inflate=widths), n_band=8, n_coarse=2)
    o, d = _rays([-0.3, 0.3, 0.55])
    hits = sampler.cast(o, d)
    torch.testing.assert_close(hits.width, torch.tensor([0.02, 0.08, 0.08]))
    lo, hi = sampler.band(hits)
    t_hit = 3.0 - np.sqrt(0.5**2 - 0.3**2)  # the sphere's front at x = +-0.3
    assert lo[:2].tolist() == pytest.approx([t_hit - 0.02, t_hit - 0.08], abs=5e-3)
    assert hi[:2].tolist() == pytest.approx([t_hit + 0.02, t_hit + 0.08], abs=5e-3)
    # passing 0.05 outside the sphere: inside the 0.08 copy for 2 sqrt(0.58^2 - 0.55^2)
    assert (hi[2] - lo[2]).item() == pytest.approx(2 * np.sqrt(0.58**2 - 0.55**2), abs=0.02)
    assert sampler.d == pytest.approx(0.08)  # the widest: what the inflated copy spans


def test_update_vertices_moves_the_hit():
    mesh = _sphere(0.5)
    rc = ProxyRaycaster(mesh, inflate=0.02)
    o, d = _rays([0.0])
    t0 = rc.cast(o, d).t_hit.item()
    rc.update_vertices(np.asarray(mesh.vertices) + np.array([0.0, 0.0, 0.2]))
    t1 = rc.cast(o, d).t_hit.item()
    assert abs((t1 - t0) - 0.2) < 1e-4


def test_band_around_a_proxy_moved_beyond_the_sphere():
    # a ball of radius 0.5 lifted to reach z = 1.3 (an edit that makes the object taller than
    # the unit sphere): the ray through its top part must still get a band around the hit
    mesh = _sphere(0.5)
    rc = ProxyRaycaster(mesh, inflate=0.02)
    rc.update_vertices(np.asarray(mesh.vertices) + np.array([0.0, 0.0, 0.8]))
    o = torch.tensor([[0.0, -3.0, 1.15]])  # passes above the unit sphere, through the ball
    d = torch.tensor([[0.0, 1.0, 0.0]])
    hits = rc.cast(o, d)
    t_hit = 3.0 - np.sqrt(0.5**2 - 0.35**2)  # the ball's front at height 1.15
    assert abs(hits.t_hit.item() - t_hit) < 5e-3
    assert hits.hit.item()
    lo, hi = BandSampler(rc, n_band=8, n_coarse=2).band(hits)
    assert lo.item() == pytest.approx(t_hit - 0.02, abs=5e-3)
    assert hi.item() == pytest.approx(t_hit + 0.02, abs=5e-3)


def test_sample_pdf_known_pdf():
    bins = torch.tensor([[0.0, 1.0, 2.0], [0.0, 1.0, 2.0]])
    w = torch.tensor([[0.0, 1.0], [1.0, 3.0]])
    s = sample_pdf(bins, w, 8)
    # all mass in the second bin: samples spread over [1, 2] at the CDF levels (i + 0.5) / 8
    expected = 1.0 + (torch.arange(8) + 0.5) / 8
    torch.testing.assert_close(s[0], expected, atol=1e-4, rtol=0)
    # 1/4 of the mass in [0, 1]: levels 1/16, 3/16 land there, at 4u
    assert (s[1] < 1.0).sum() == 2
    torch.testing.assert_close(s[1, :2], torch.tensor([0.25, 0.75]), atol=1e-4, rtol=0)
    rnd = sample_pdf(bins[1:].expand(2000, 3), w[1:].expand(2000, 2), 4, perturb=True)
    frac = (rnd < 1.0).float().mean().item()
    assert abs(frac - 0.25) < 0.02


def test_uniform_sampler_coarse_plus_importance():
    sampler = UniformSampler(n_coarse=64, n_importance=128)
    o, d = _rays([0.0, 2.0])
    hits = sampler.cast(o, d)
    assert hits.hit.tolist() == [True, False]
    sub = hits[hits.hit]
    t, delta = sampler.sample(sub)
    assert t.shape == (1, 64)
    w = torch.zeros(1, 64)
    w[0, 20] = 1.0  # all weight in one coarse bin
    t2, delta2 = sampler.importance(sub, t, w)
    assert t2.shape == (1, 192)
    assert torch.all(t2[:, 1:] >= t2[:, :-1])
    edges_lo = 2.0 + 2.0 * 20 / 64
    fine = t2[0][(t2[0] > edges_lo) & (t2[0] < edges_lo + 2.0 / 64)]
    assert fine.numel() >= 128
    torch.testing.assert_close(delta2.sum(), torch.tensor(2.0), atol=1e-4, rtol=0)


def _solid_sphere_field(points, dirs):
    inside = points.norm(dim=-1) < 0.5
    sigma = inside.float() * 1e4
    rgb = torch.tensor([1.0, 0.0, 0.0]).expand(points.shape[0], 3)
    return {"sigma": sigma, "rgb": rgb, "feat": points[:, :1] * 0 + 2.0}


def test_render_rays_band_and_uniform_agree_on_a_solid_sphere():
    o, d = _rays([0.0, 0.2, 0.9])
    bg = torch.tensor([0.0, 0.0, 1.0])
    band = BandSampler(ProxyRaycaster(_sphere(0.5), inflate=0.05), n_band=32, n_coarse=4)
    for sampler in (band, UniformSampler(64, 128)):
        out = render_rays(_solid_sphere_field, o, d, sampler, bg)
        torch.testing.assert_close(out["opacity"], torch.tensor([1.0, 1.0, 0.0]), atol=1e-3, rtol=0)
        torch.testing.assert_close(out["rgb"][0], torch.tensor([1.0, 0.0, 0.0]), atol=1e-3, rtol=0)
        torch.testing.assert_close(out["rgb"][2], bg)
        torch.testing.assert_close(
            out["feat"][:, 0], torch.tensor([2.0, 2.0, 0.0]), atol=1e-3, rtol=0
        )
        expect = 3.0 - np.sqrt(0.25 - 0.04)
        assert abs(out["depth"][0].item() - 2.5) < 0.01
        assert abs(out["depth"][1].item() - expect) < 0.01
    assert band.samples_per_ray < 192 / 4


def test_render_image_shapes():
    from render.cameras import Camera, look_at

    cam = Camera(
        16, 12, 20.0, 20.0, 8.0, 6.0, camera_to_world=look_at(np.array([0, -3.0, 0]), np.zeros(3))
    )
    sampler = BandSampler(ProxyRaycaster(_sphere(0.5), inflate=0.05), n_band=8, n_coarse=2)
    img = render_image(cam, _solid_sphere_field, sampler, torch.ones(3), chunk=50)
    assert img["rgb"].shape == (12, 16, 3) and img["opacity"].shape == (12, 16)
    assert img["feat"].shape == (12, 16, 1)
    assert abs(img["opacity"][6, 8] - 1.0) < 1e-3 and img["opacity"][0, 0] == 0.0
    assert abs(img["z"][6, 8] - 2.5) < 0.02


def test_chunked_render_keeps_extra_channels_of_chunks_without_hits():
    """A chunk whose rays all miss still contributes zero rows to every extra channel."""
    import torch

    from render.renderer import render_rays_chunked

    class Hits:
        def __init__(self, hit):
            self.hit = hit

        def __getitem__(self, idx):
            return Hits(self.hit[idx])

    class HalfSampler:  # the first 4 rays miss, the last 4 hit (a delta sample at t = 1)
        def cast(self, origins, dirs):
            return Hits(origins[:, 0] > 0)

        def sample(self, hits, perturb, generator):
            n = len(hits.hit)
            return torch.ones(n, 1), torch.full((n, 1), 1e10)

    def query(points, dirs):
        n = len(points)
        return {"sigma": torch.full((n,), 50.0), "rgb": torch.ones(n, 3), "feat": torch.ones(n, 5)}

    origins = torch.tensor([[-1.0, 0, 0]] * 4 + [[1.0, 0, 0]] * 4)
    dirs = torch.tensor([[0, 0, 1.0]] * 8)
    out = render_rays_chunked(query, origins, dirs, HalfSampler(), background=(0, 0, 0), chunk=4)
    assert out["feat"].shape == (8, 5)
    assert torch.all(out["feat"][:4] == 0) and torch.allclose(out["feat"][4:], torch.ones(4, 5))
    assert torch.all(out["opacity"][:4] == 0) and torch.allclose(out["opacity"][4:], torch.ones(4))


def test_render_image_renders_silhouette_pixels_again():
    """supersample 2 with the default edge_supersample (4): a pixel whose 2 x 2 rays' opacities
    differ is exactly the 4 x 4 render's pixel, every other pixel the 2 x 2 render's; the
    opacity's sum comes closer to the sphere's projected area (35.90 px^2)."""
    from render.cameras import Camera, look_at

    cam = Camera(
        16, 12, 20.0, 20.0, 8.0, 6.0, camera_to_world=look_at(np.array([0, -3.0, 0]), np.zeros(3))
    )
    sampler = BandSampler(ProxyRaycaster(_sphere(0.5), inflate=0.05), n_band=8, n_coarse=2)
    area = np.pi * (20.0 * np.tan(np.arcsin(0.5 / 3.0))) ** 2

    def render(s, t=None, subpixels=()):
        white = torch.ones(3)
        return render_image(
            cam, _solid_sphere_field, sampler, white, 16384, None, s, subpixels, edge_supersample=t
        )

    two, four, both = render(2, 2, ("opacity",)), render(4, 4), render(2)
    sub = two["opacity_subpixels"][..., 0]  # [4, H, W]
    again = sub.max(axis=0) - sub.min(axis=0) > 0.05
    assert 0 < again.sum() < 0.3 * again.size
    assert np.array_equal(both["rendered_again"], again) and not two["rendered_again"].any()
    for k in ("rgb", "opacity", "z"):
        np.testing.assert_allclose(both[k][again], four[k][again], atol=1e-5)
        np.testing.assert_allclose(both[k][~again], two[k][~again], atol=1e-6)
    assert abs(both["opacity"].sum() - area) < abs(two["opacity"].sum() - area)
    assert both["samples_per_pixel"] > two["samples_per_pixel"]
    assert render(1)["opacity"].shape == (12, 16)  # one ray per pixel: nothing rendered again


def test_render_image_supersample_integrates_each_pixel():
    """s x s rays per pixel, box-filtered: the rendered opacity sums to the sphere's projected
    area (pi (f tan(asin(r / d)))^2 = 35.90 px^2 for r 0.5, d 3, f 20), which one ray per
    pixel only counts in whole pixels; a pixel fully inside stays opaque red."""
    from render.cameras import Camera, look_at

    cam = Camera(
        16, 12, 20.0, 20.0, 8.0, 6.0, camera_to_world=look_at(np.array([0, -3.0, 0]), np.zeros(3))
    )
    sampler = BandSampler(ProxyRaycaster(_sphere(0.5), inflate=0.05), n_band=8, n_coarse=2)
    area = np.pi * (20.0 * np.tan(np.arcsin(0.5 / 3.0))) ** 2
    one = render_image(cam, _solid_sphere_field, sampler, torch.ones(3))
    five = render_image(  # the s x s rays alone (silhouette pixels not rendered again)
        cam, _solid_sphere_field, sampler, torch.ones(3), supersample=5, edge_supersample=5
    )
    assert five["rgb"].shape == (12, 16, 3) and five["feat"].shape == (12, 16, 1)
    assert set(np.unique(np.round(one["opacity"], 3))) <= {0.0, 1.0}
    assert 0 < np.sum((five["opacity"] > 0.01) & (five["opacity"] < 0.99))  # soft edge
    assert abs(five["opacity"].sum() - area) < 0.5
    assert abs(five["opacity"].sum() - area) < abs(one["opacity"].sum() - area)
    np.testing.assert_allclose(five["rgb"][6, 8], [1.0, 0.0, 0.0], atol=1e-3)
    np.testing.assert_allclose(five["rgb"][:, :, 1], 1.0 - five["opacity"], atol=1e-3)
    # depth is that of what a pixel sees: an edge pixel stays on the sphere (z in [2.5, 3])
    edge = (five["opacity"] > 0.05) & (five["opacity"] < 0.95)
    assert np.all((five["z"][edge] > 2.5 - 1e-3) & (five["z"][edge] < 3.0 + 1e-3))
    assert np.all(five["z"][five["opacity"] == 0] == 0)
    # the sub-pixel images: image (i, j) is ray (i, j) of every pixel, i.e. every 5th pixel of
    # a 5x larger camera's one-ray render, starting at row i, column j; their mean is the pixel
    subs = render_image(
        cam, _solid_sphere_field, sampler, torch.ones(3), supersample=5, subpixels=("rgb",)
    )  # with the silhouette pixels rendered again (10 x 10): the sub-pixel images stay 5 x 5
    assert subs["rgb_subpixels"].shape == (25, 12, 16, 3) and "opacity_subpixels" not in subs
    np.testing.assert_allclose(subs["rgb_subpixels"].mean(axis=0), five["rgb"], atol=1e-6)
    big = render_image(cam.resized(80, 60), _solid_sphere_field, sampler, torch.ones(3))
    for i, j in ((0, 0), (1, 3), (4, 2)):
        np.testing.assert_allclose(subs["rgb_subpixels"][5 * i + j], big["rgb"][i::5, j::5])


class _NoWindow:
    """A sampler without `pixel_window`: every pixel's ray is cast."""

    def __init__(self, sampler):
        self.sampler = sampler

    def cast(self, origins, dirs):
        return self.sampler.cast(origins, dirs)

    def sample(self, hits, perturb=False, generator=None):
        return self.sampler.sample(hits, perturb, generator)


def test_pixel_window_culls_nothing_the_proxy_can_hit():
    """A whole-image render casts only the inflated proxy's pixel window: every channel equals
    the render that casts every pixel, bit for bit (the sphere off-centre, so the window is a
    corner of the image); a camera inside the proxy's hull gets no window."""
    from render.cameras import Camera, look_at

    cam = Camera(
        40, 30, 20.0, 20.0, 20.0, 15.0, camera_to_world=look_at(np.array([0, -3.0, 0]), np.zeros(3))
    )
    sphere = _sphere(0.3).translate((0.6, 0.0, 0.3))
    sampler = BandSampler(ProxyRaycaster(sphere, inflate=0.05), n_band=8, n_coarse=2)
    row0, row1, col0, col1 = sampler.pixel_window(cam)
    assert 0 < (row1 - row0) * (col1 - col0) < 0.25 * 40 * 30
    # the sphere's centre (0.6, 0, 0.3) at distance 3: u = 20 + 20 * 0.2, v = 15 - 20 * 0.1
    assert col0 < 24 < col1 and row0 < 13 < row1
    for s in (1, 2):
        culled = render_image(cam, _solid_sphere_field, sampler, torch.ones(3), supersample=s)
        full = render_image(
            cam, _solid_sphere_field, _NoWindow(sampler), torch.ones(3), supersample=s
        )
        assert culled["opacity"].sum() > 1.0
        for k in ("rgb", "opacity", "depth", "z", "feat"):
            np.testing.assert_array_equal(culled[k], full[k])
    inside = Camera(8, 6, 8.0, 8.0, 4.0, 3.0, camera_to_world=look_at([0.6, 0.0, 0.3], [0, 0, 0]))
    assert sampler.pixel_window(inside) is None
    assert UniformSampler().pixel_window(cam) is None
