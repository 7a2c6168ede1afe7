"""Texture editing: the compositor, deferred back-propagation against direct back-propagation, the
coarse-to-fine window, the kept template samples against the renderer, the proxy-lifted masks,
and a tiny end-to-end texture edit (its loss falls, colours change in the painted part more than
elsewhere, resume, baselines, the CLI and the edit's scene)."""

from __future__ import annotations

import dataclasses
import json
import math
import shutil

import numpy as np
import pytest
import torch
from feature_run_helpers import TINY_TEXTURE_EDIT

import sine_cli
from edit.compositor import EPS, HEADS, TAU, Compositor, composite_hwc
from edit.deferred import assemble, deferred_backward, direct_backward, image_tiles, ray_chunks
from edit.editing_field import EditingField, edited_query
from edit.geometry_config import GeometryEditConfig
from edit.scene import load_scene
from edit.targets import recolor_region, write_rgba
from edit.texture_config import TextureEditConfig
from edit.texture_edit import run_texture_edit
from edit.texture_field import TextureField, cosine_window
from edit.texture_training import edited_image
from edit.texture_views import (
    LiftedRegion,
    ViewSamples,
    render_gate,
    render_modification,
    sample_view,
)
from recon.fit import load_fitted
from recon.fit_proxy import make_sampler
from recon.rundir import RunDir
from render.cameras import Camera, look_at
from render.hashgrid import HashGridConfig
from render.io import (
    load_torch,
    read_image,
    read_label_map,
    read_mask,
    save_torch,
    write_image,
    write_mask,
)
from render.renderer import render_image, render_rays
from render.sampler import UniformSampler
from render.template_field import TemplateField, TemplateFieldConfig, freeze

SMALL_GRID = HashGridConfig(n_levels=4, log2_table=8, max_resolution=32)
VIEW, OTHER = 2, 3  # tiny run: the car's side; a view a quarter turn away
PART = 1  # the car's body


# ---- compositor -----------------------------------------------------------------------------
def test_compositor_shapes_and_identity_start():
    torch.manual_seed(0)
    comp = Compositor()
    template = torch.rand(2, 3, 17, 23) * 0.9 + 0.05  # odd sizes: the decoder matches the skip
    assert comp(template, torch.zeros_like(template)).shape == (2, 3, 17, 23)
    # before training: I = I_o when m' = 0, and the plain sum I_o + I_m otherwise
    assert torch.allclose(comp(template, torch.zeros_like(template)), template, atol=1e-5)
    mod = torch.full_like(template, 0.02)
    assert torch.allclose(comp(template, mod), (template + mod).clamp(EPS, 1 - EPS), atol=1e-5)
    # the modification reaches the image from the first step (the head is still zero)
    mod.requires_grad_(True)
    comp(template, mod).sum().backward()
    assert mod.grad.abs().min() > 0
    # encoder 6 -> 16 -> 32, decoder back to 16 with the skip, 3x3 convolutions, 3 channels out
    convs = [comp.enc1, comp.enc2, comp.dec2, comp.dec1, comp.head]
    assert [(c.in_channels, c.out_channels) for c in convs] == [
        (6, 16),
        (16, 32),
        (32, 16),
        (32, 16),
        (16, 3),
    ]
    assert all(c.kernel_size == (3, 3) for c in convs)
    # once trained (any head), the output is a sigmoid: inside (0, 1)
    with torch.no_grad():
        comp.head.weight.normal_(0, 0.3)
    mod = torch.randn_like(template)
    mod[..., :5] = 0.0  # no modification in the first 5 columns
    out = comp(template, mod)
    assert out.min() > 0 and out.max() < 1 and not torch.allclose(out, template, atol=1e-2)
    # ... and where F_dT modifies nothing the gate keeps the template, whatever the weights
    assert torch.allclose(out[..., :5], template[..., :5], atol=1e-5)
    with pytest.raises(ValueError, match="two"):
        comp(template, template[:, :2])
    # the gate by hand: g = 1 - exp(-(|I_m|_1 / TAU)^2) scales the head's residual
    comp = Compositor()
    with torch.no_grad():
        comp.head.bias.fill_(1.0)  # residual 1 everywhere
    t = torch.full((1, 3, 4, 4), 0.5)
    m = torch.zeros_like(t)
    m[:, 0] = TAU  # |I_m|_1 = TAU: g = 1 - 1/e
    g = 1 - math.exp(-1)
    expected = torch.sigmoid(torch.logit(torch.tensor([0.5 + TAU, 0.5, 0.5])) + g)
    assert torch.allclose(comp(t, m)[0, :, 2, 2], expected, atol=1e-6)
    # a given region is g itself: 0 keeps the plain sum, 1 adds the whole residual
    region = torch.zeros(1, 1, 4, 4)
    region[..., 2:, :] = 1.0
    out = comp(t, m, region)
    assert torch.allclose(out[0, :, 0, 0], torch.tensor([0.5 + TAU, 0.5, 0.5]), atol=1e-6)
    full = torch.sigmoid(torch.logit(torch.tensor([0.5 + TAU, 0.5, 0.5])) + 1.0)
    assert torch.allclose(out[0, :, 3, 3], full, atol=1e-6)


def test_affine_head_starts_at_the_plain_sum_and_applies_one_colour_transform():
    torch.manual_seed(0)
    comp = Compositor(head="affine")
    assert comp.head.out_channels == 12
    template = torch.rand(1, 3, 6, 8) * 0.9 + 0.05
    mod = torch.full_like(template, 0.02)
    assert torch.allclose(comp(template, mod), (template + mod).clamp(EPS, 1 - EPS), atol=1e-5)
    # A = P - 1 with P the channel permutation (R, G, B) -> (B, R, G) (a hue rotation by 120
    # degrees), b = 0: where the gate is 1 the output is the base with its channels permuted,
    # whatever each pixel's shade; where it is 0, the base
    perm = torch.tensor([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])
    with torch.no_grad():
        comp.head.bias[:9] = (perm - torch.eye(3)).flatten()
    region = torch.zeros(1, 1, 6, 8)
    region[..., 3:, :] = 1.0
    base = (template + mod).clamp(EPS, 1 - EPS)
    out = comp(template, mod, region)
    assert torch.allclose(out[..., 3:, :], base[:, [2, 0, 1], 3:, :], atol=1e-5)
    assert torch.allclose(out[..., :3, :], base[..., :3, :], atol=1e-6)
    # A = diag(-0.5, 0, -0.5): grey shades (v, v, v) become (v / 2, v, v / 2), a green of the
    # same shade: the map is linear in RGB, so every shade takes it alike
    with torch.no_grad():
        comp.head.bias[:9] = torch.diag(torch.tensor([-0.5, 0.0, -0.5])).flatten()
    grey = torch.linspace(0.1, 0.9, 8).expand(1, 3, 6, 8).contiguous()
    out = comp(grey, torch.zeros_like(grey), torch.ones(1, 1, 6, 8))
    expected = torch.stack([grey[:, 0] / 2, grey[:, 1], grey[:, 2] / 2], dim=1)
    assert torch.allclose(out, expected, atol=1e-6)
    # out of [0, 1]: clamped, and the gradient still pulls the pixel back
    with torch.no_grad():
        comp.head.bias[:9] = 0.0
        comp.head.bias[9:] = 0.5  # b: +0.5 on every channel
    mod = torch.zeros_like(grey).requires_grad_(True)
    out = comp(grey, mod, torch.ones(1, 1, 6, 8))
    assert out.max() == 1.0 and out.min() > 0.5
    out.sum().backward()
    assert (mod.grad == 1.0).all()
    # a saved compositor comes back with its head's kind and width
    again = Compositor.for_state(comp.state_dict())
    assert again.kind == "affine" and again.head.out_channels == 12
    assert Compositor.for_state(Compositor(width=8).state_dict()).enc1.out_channels == 8
    with pytest.raises(ValueError, match="head"):
        Compositor(head="quadratic")


def test_affine_head_transforms_only_the_parts_share_of_a_rim_pixel():
    """With the part's share P of I_o given, A acts on P + I_m and b is weighed by g: a pixel
    half part (colour p) and half background (colour q) changes by (A p + b) / 2; inside the
    part (g = 1, P = I_o) it is the transform of the whole pixel, as without P."""
    comp = Compositor(head="affine")
    a = torch.tensor([[0.0, 0.25, 0.0], [-0.25, 0.0, 0.0], [0.0, 0.0, -0.25]])
    b = torch.tensor([0.05, 0.0, -0.05])  # p -> (0.95, 0.2, 0.1): no clamping
    with torch.no_grad():
        comp.head.bias[:9] = a.flatten()
        comp.head.bias[9:] = b
    p, q = torch.tensor([0.8, 0.4, 0.2]), torch.tensor([0.1, 0.3, 0.6])
    template = torch.stack([(p + q) / 2, p], dim=1)[None, :, None, :]  # [1, 3, 1, 2]
    part = torch.stack([p / 2, p], dim=1)[None, :, None, :]
    region = torch.tensor([0.5, 1.0]).reshape(1, 1, 1, 2)
    mod = torch.zeros_like(template)
    out = comp(template, mod, region, part)[0, :, 0]  # [3, 2]
    assert torch.allclose(out[:, 0], (p + q) / 2 + (a @ p + b) / 2, atol=1e-6)
    assert torch.allclose(out[:, 1], p + a @ p + b, atol=1e-6)
    assert torch.allclose(out[:, 1], comp(template, mod, region)[0, :, 0, 1], atol=1e-6)
    # the whole pixel transformed instead: the background's share changes too
    whole = comp(template, mod, region)[0, :, 0, 0]
    assert torch.allclose(whole, (p + q) / 2 + (a @ ((p + q) / 2) + b) / 2, atol=1e-6)
    assert (whole - out[:, 0]).abs().max() > 0.03


def composite_columns(comp, template, g, part):
    """The compositor on pixels given as columns: I_o and P [N, 3], g [N], I_m = 0 -> [N, 3]."""

    def as_image(x):  # [N, C] -> [1, C, 1, N]
        return x.T.reshape(1, x.shape[1], 1, x.shape[0])

    image = as_image(template)
    out = comp(image, torch.zeros_like(image), as_image(g[:, None]), as_image(part))
    return out[0, :, 0].T


def test_the_shared_transform_starts_at_the_least_squares_fit_to_the_target():
    """A target made by one colour transform (the channel permutation of a 120-degree hue turn,
    plus an offset) on the part's pixels: the fit recovers it, and the compositor then renders
    the target from the template (I_m = 0), rim pixels included (their part's share only)."""
    from edit.compositor import fit_shared_transform

    gen = torch.Generator().manual_seed(0)
    perm = torch.tensor([[0.0, 0, 1], [1, 0, 0], [0, 1, 0]])
    a, b = perm - torch.eye(3), torch.tensor([0.02, -0.01, 0.03])
    n = 200
    background = torch.tensor([0.9, 0.9, 0.9])
    own = torch.rand(n, 3, generator=gen) * 0.8 + 0.1  # the part's colours
    g = torch.ones(n)
    g[:40] = torch.rand(40, generator=gen)  # rim pixels: part of each is the background
    part = g[:, None] * own  # [N, 3] the part's share of I_o
    template = part + (1 - g[:, None]) * background
    target = template + part @ a.T + g[:, None] * b
    comp = Compositor(head="affine")
    residual = fit_shared_transform(comp, template, target, g, part, ridge=1e-9)
    assert residual.abs().max() < 1e-5
    assert torch.allclose(comp.head.bias[:9].reshape(3, 3), a, atol=1e-4)
    assert torch.allclose(comp.head.bias[9:], b, atol=1e-4)

    out = composite_columns(comp, template, g, part)
    assert torch.allclose(out, target.clamp(0, 1), atol=1e-4)
    # without the part's share: the transform of the whole pixel, weighed by g
    whole = template + g[:, None] * (template @ a.T + b)
    comp = Compositor(head="affine")
    assert fit_shared_transform(comp, template, whole, g, ridge=1e-9).abs().max() < 1e-5
    assert torch.allclose(comp.head.bias[:9].reshape(3, 3), a, atol=1e-4)
    with pytest.raises(ValueError, match="affine"):
        fit_shared_transform(Compositor(), template, target, g)


def test_the_quadratic_term_is_fitted_and_rendered_with_the_parts_share():
    """A target made by a quadratic colour map of the part's own colour c (A c + b + Q c c^T
    terms) on pixels partly the part's (share g): the fit recovers A, b and Q, the compositor
    renders the target (a rim pixel's change is g times the part pixel's), it starts as no
    change, and a saved compositor comes back with its quadratic term."""
    from edit.compositor import PAIRS, fit_shared_transform

    gen = torch.Generator().manual_seed(1)
    n = 300
    a = torch.randn(3, 3, generator=gen) * 0.2
    b = torch.tensor([0.05, -0.02, 0.01])
    q = torch.randn(3, 6, generator=gen) * 0.2
    own = torch.rand(n, 3, generator=gen) * 0.8 + 0.1  # the part's colours
    g = torch.ones(n)
    g[:60] = torch.rand(60, generator=gen) * 0.9 + 0.1  # rim pixels
    part = g[:, None] * own
    template = part + (1 - g[:, None]) * torch.tensor([0.2, 0.5, 0.7])
    products = torch.stack([own[:, i] * own[:, j] for i, j in PAIRS], dim=1)  # [N, 6]
    change = own @ a.T + b + products @ q.T  # [N, 3] a whole part pixel's change
    target = template + g[:, None] * change
    comp = Compositor(head="affine", quadratic=True)
    assert comp(template.T[None, :, None], torch.zeros(1, 3, 1, n)).allclose(
        template.T[None, :, None].clamp(1e-4, 1 - 1e-4)
    )  # untrained: no change
    residual = fit_shared_transform(comp, template, target, g, part, ridge=1e-9)
    assert residual.abs().max() < 1e-5
    assert torch.allclose(comp.quadratic, q, atol=1e-4)
    assert torch.allclose(comp.head.bias[:9].reshape(3, 3), a, atol=1e-4)

    out = composite_columns(comp, template, g, part)
    assert torch.allclose(out, target.clamp(0, 1), atol=1e-4)
    linear = Compositor(head="affine")
    assert fit_shared_transform(linear, template, target, g, part, ridge=1e-9).abs().max() > 0.01
    again = Compositor.for_state(comp.state_dict())
    assert (
        again.quadratic is not None and Compositor.for_state(linear.state_dict()).quadratic is None
    )
    with pytest.raises(ValueError, match="affine"):
        Compositor(quadratic=True)


def test_the_parts_share_is_used_by_the_affine_head_with_the_gate_only():
    from edit.texture_config import uses_part_colour

    assert uses_part_colour(TextureEditConfig())  # the defaults: affine head, gate
    for change in ({"compositor_head": "residual"}, {"gate": False}, {"compositor": False}):
        assert not uses_part_colour(TextureEditConfig(**change)), change
    assert not uses_part_colour(TextureEditConfig(part_colour=False))


def test_the_gate_has_one_voxel_per_pixel_footprint_by_default():
    """Cameras 4 units from the centre with a focal length of 400 px see 0.01 units per pixel:
    over the gate's [-1, 1]^3 that is 200 voxels a side; coarser cameras get the floor of 128,
    finer ones the ceiling of 384; an explicit resolution wins."""
    from edit.texture_config import GATE_RESOLUTION_AUTO, gate_resolution

    def cameras(focal):
        return [Camera(64, 64, focal, focal, 32, 32, look_at([4.0, 0.0, 0.0], [0.0] * 3))]

    auto = TextureEditConfig()
    assert auto.gate_resolution == 0 and GATE_RESOLUTION_AUTO == (128, 384)
    assert gate_resolution(auto, cameras(400.0)) == 200
    assert gate_resolution(auto, cameras(100.0)) == 128
    assert gate_resolution(auto, cameras(2000.0)) == 384
    assert gate_resolution(TextureEditConfig(gate_resolution=96), cameras(400.0)) == 96


def test_affine_head_shared_transform_has_its_own_learning_rate():
    from edit.texture_training import texture_parts

    template = TemplateField(TemplateFieldConfig(grid=SMALL_GRID))
    cfg = TextureEditConfig(compositor_head="affine", lr_compositor=1e-3, lr_transform=0.05)
    _, comp, _, groups = texture_parts(template, cfg, torch.device("cpu"))
    lrs = {g["name"]: (g["lr"], g["params"]) for g in groups}
    shared = lrs["transform"][1]
    assert lrs["transform"][0] == 0.05 and len(shared) == 2  # the bias and the quadratic term
    assert {id(p) for p in shared} == {id(comp.head.bias), id(comp.quadratic)}
    cfg_linear = dataclasses.replace(cfg, quadratic_transform=False)
    _, linear, _, groups_linear = texture_parts(template, cfg_linear, torch.device("cpu"))
    assert linear.quadratic is None
    assert [p is linear.head.bias for p in groups_linear[-1]["params"]] == [True]
    assert lrs["compositor"][0] == 1e-3 and len(lrs["compositor"][1]) == 9  # 5 convs, one bias out
    cfg = dataclasses.replace(cfg, compositor_head="residual")
    _, comp, _, groups = texture_parts(template, cfg, torch.device("cpu"))
    assert [g["name"] for g in groups] == ["grid", "mlp", "compositor"]
    # without lr_compositor the UNet learns at its head's rate: the affine head's is half
    for head, lr in (("affine", 2.5e-3), ("residual", 5e-3)):
        cfg = TextureEditConfig(compositor_head=head)
        _, _, _, groups = texture_parts(template, cfg, torch.device("cpu"))
        assert {g["name"]: g["lr"] for g in groups}["compositor"] == lr


def test_no_transform_is_fitted_without_an_aligned_target_or_the_affine_head():
    from edit.texture_config import fits_transform, options_in_effect

    cfg = TextureEditConfig(fit_transform=True)
    assert fits_transform(cfg) and fits_transform(options_in_effect(cfg, None))
    assert not fits_transform(options_in_effect(cfg, "photo.png"))  # a reference photo
    for change in ({"compositor_head": "residual"}, {"gate": False}, {"compositor": False}):
        assert not fits_transform(dataclasses.replace(cfg, **change)), change


def test_composite_hwc_without_compositor_is_the_clamped_sum():
    template = torch.tensor([[[0.2, 0.5, 0.9]]])
    mod = torch.tensor([[[0.3, -0.7, 0.4]]])
    assert torch.allclose(composite_hwc(None, template, mod), torch.tensor([[[0.5, 0.0, 1.0]]]))
    assert composite_hwc(Compositor(), template, mod).shape == (1, 1, 3)


# ---- coarse-to-fine -------------------------------------------------------------------------
def test_cosine_window_by_hand():
    # w_l(a) = (1 - cos(pi * clamp(a - l, 0, 1))) / 2, level 0 always 1
    assert torch.allclose(cosine_window(4, 1.5), torch.tensor([1.0, 0.5, 0.0, 0.0]))
    expected = (1 - math.cos(math.pi * 0.25)) / 2  # 0.1464...
    assert torch.allclose(cosine_window(4, 2.25), torch.tensor([1.0, 1.0, expected, 0.0]))
    assert torch.allclose(cosine_window(4, 0.0), torch.tensor([1.0, 0.0, 0.0, 0.0]))
    assert torch.allclose(cosine_window(4, 9.0), torch.ones(4))
    field = TextureField(SMALL_GRID)  # 4 levels, window from 1 to 4 over training
    field.set_progress(0.0)
    assert torch.allclose(field.window, torch.tensor([1.0, 0.0, 0.0, 0.0]))
    field.set_progress(0.5)  # alpha = 1 + 3 * 0.5 = 2.5
    assert torch.allclose(field.window, torch.tensor([1.0, 1.0, 0.5, 0.0]))
    field.set_progress(1.0)
    assert torch.allclose(field.window, torch.ones(4))


# ---- deferred back-propagation --------------------------------------------------------------
def _random_view(h: int, w: int, seed: int, cond_dim: int = 0) -> ViewSamples:
    """A synthetic view: 0-3 samples per pixel at random points with random weights (and
    random `cond_dim` features per sample)."""
    g = torch.Generator().manual_seed(seed)
    counts = torch.randint(0, 4, (h * w,), generator=g)
    n = int(counts.sum())
    offsets = torch.zeros(h * w + 1, dtype=torch.int64)
    offsets[1:] = torch.cumsum(counts, 0)
    cam = Camera(w, h, 10.0, 10.0, w / 2, h / 2)
    return ViewSamples(
        camera=cam,
        template_rgb=torch.rand(h * w, 3, generator=g) * 0.8 + 0.1,
        opacity=torch.rand(h * w, generator=g),
        depth=torch.zeros(h * w),
        surface=torch.zeros(h * w, 3),
        points=torch.rand(n, 3, generator=g) * 1.6 - 0.8,
        weights=torch.rand(n, generator=g) * 0.5,
        pixel=torch.repeat_interleave(torch.arange(h * w), counts),
        offsets=offsets,
        features=torch.randn(n, cond_dim, generator=g) if cond_dim else None,
    )


def _grads(*modules) -> list[torch.Tensor]:
    return [p.grad.clone() for m in modules for p in m.parameters() if p.requires_grad]


@pytest.mark.parametrize(
    "cond_dim, head, part",
    [
        (0, "residual", False),
        (4, "residual", False),
        (4, "affine", False),
        (4, "affine", True),
    ],
)
def test_deferred_gradients_equal_direct_backpropagation(cond_dim, head, part):
    """Two images through F_dT (position only, or reading per-sample features) and the
    compositor, an image-space loss mixing all pixels: the parameter gradients of deferred
    back-propagation in tiles of 4 px (halo 8, F_dT on 5 samples at a time) equal those of
    direct back-propagation through the whole images at once (either compositor head; the
    affine one also with the gate g and the part's share P of I_o)."""
    torch.manual_seed(0)
    texture, comp = TextureField(SMALL_GRID, cond_dim=cond_dim), Compositor(head=head)
    with torch.no_grad():  # leave the zero start so every parameter gets a gradient
        texture.mlp[-1].weight.normal_(0, 0.5)
        comp.head.weight.normal_(0, 0.5)
    views = [_random_view(14, 11, 1, cond_dim), _random_view(9, 16, 2, cond_dim)]
    if part:
        for view in views:
            view.region = torch.rand(view.n_pixels)
            view.part_rgb = view.template_rgb * view.region[:, None]
    goal = [torch.rand(*v.size, 3) for v in views]

    def loss_fn(leaves):
        total = 0
        for leaf, g in zip(leaves, goal, strict=True):
            image = leaf["rgb"]  # [h, w, 3]
            total = total + ((image - g) ** 2).mean() + image.mean((0, 1)).pow(2).sum()
        return total, None

    # the reference: I_m of every pixel at once, one compositor pass per image, one backward
    images = []
    for view in views:
        h, w = view.size
        mod = render_modification(view, texture, None).reshape(h, w, 3)  # one plain graph
        template_rgb = view.template_rgb.reshape(h, w, 3)
        region = None if view.region is None else view.region.reshape(h, w)
        part_rgb = None if view.part_rgb is None else view.part_rgb.reshape(h, w, 3)
        images.append({"rgb": composite_hwc(comp, template_rgb, mod, region, part_rgb)})
    loss_direct, _ = loss_fn(images)
    loss_direct.backward()
    direct = _grads(texture, comp)
    texture.zero_grad(), comp.zero_grad()
    tiled = [edited_image(v, texture, comp, tile=4, chunk=5) for v in views]
    assert len(tiled[0].pieces) == 4 * 3
    loss_deferred, _ = deferred_backward(tiled, loss_fn)
    deferred = _grads(texture, comp)
    assert torch.allclose(loss_direct, loss_deferred)
    assert len(direct) == len(deferred) == 5 + 10  # table, 2 linear layers; 5 convs
    for a, b in zip(direct, deferred, strict=True):
        assert a.abs().max() > 0
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-7), (a - b).abs().max()


def test_deferred_gradients_through_volume_rendering():
    """Chunks of rays: `render(start, stop)` renders rays through a field with the renderer."""
    torch.manual_seed(0)
    field = TemplateField(TemplateFieldConfig(grid=SMALL_GRID, density_activation="softplus"))
    cam = Camera(6, 5, 6.0, 6.0, 3.0, 2.5, look_at(np.array([0.0, -2.5, 0.3]), np.zeros(3)))
    o, d = (torch.from_numpy(a) for a in cam.rays())
    sampler = UniformSampler(8, 0)

    def render(a, b):
        return {"rgb": render_rays(field, o[a:b], d[a:b], sampler, torch.ones(3))["rgb"]}

    def loss_fn(leaves):
        img = leaves[0]["rgb"]
        return (img.std(0) ** 2).sum() + (img[:-1] * img[1:]).mean(), None

    direct_backward([ray_chunks(render, 30, 30)], loss_fn)
    direct = _grads(field)
    field.zero_grad()
    deferred_backward([ray_chunks(render, 30, 4)], loss_fn)
    for a, b in zip(direct, _grads(field), strict=True):
        assert torch.allclose(a, b, rtol=1e-4, atol=1e-7), (a - b).abs().max()


def test_image_tiles_cover_the_image_once_with_even_halo_boxes():
    calls = []

    def render(y0, y1, x0, x1):
        calls.append((y0, y1, x0, x1))
        ys, xs = torch.meshgrid(torch.arange(y0, y1), torch.arange(x0, x1), indexing="ij")
        return {"yx": torch.stack([ys, xs], -1).float()}

    image = image_tiles(render, 10, 7, tile=4, halo=2)
    full = assemble(image)["yx"]
    ys, xs = torch.meshgrid(torch.arange(10), torch.arange(7), indexing="ij")
    assert torch.equal(full, torch.stack([ys, xs], -1).float())
    assert calls[0] == (0, 6, 0, 6) and calls[3] == (2, 10, 2, 7)  # grown by 2, clipped
    assert all(c[0] % 2 == 0 and c[2] % 2 == 0 for c in calls)


def test_texture_field_reads_its_condition_and_reloads_with_its_width():
    """F_dT with a condition: different features at the same point give different colours, a
    missing condition is an error; `EditingField.from_state` rebuilds either layout (a state
    saved before F_dT had a condition loads as position-only)."""
    torch.manual_seed(0)
    with_cond = EditingField(SMALL_GRID, texture_cond=5)
    with torch.no_grad():
        with_cond.texture.mlp[-1].weight.normal_(0, 0.5)
    x = torch.rand(6, 3) - 0.5
    a, b = torch.randn(6, 5), torch.randn(6, 5)
    assert (with_cond.texture(x, a) - with_cond.texture(x, b)).abs().max() > 1e-3
    with pytest.raises(ValueError, match="condition"):
        with_cond.texture(x)
    for field, cond in ((with_cond, a), (EditingField(SMALL_GRID), None)):
        reloaded = EditingField.from_state(SMALL_GRID, field.state_dict())
        assert reloaded.texture.cond_dim == (0 if cond is None else 5)
        assert torch.equal(reloaded.texture(x, cond), field.texture(x, cond))


# ---- views kept for F_dT against the renderer ------------------------------------------------
@pytest.mark.parametrize("features", [False, True])
def test_sample_view_matches_the_renderer(tiny_fitted_run, features):
    """I_o of the kept view is the template's rendering; with every sample kept, I_m is the
    renderer's "mod" channel through the editing field (training renders what the scene does),
    also when F_dT reads the template's geometry feature kept per sample."""
    torch.manual_seed(0)
    template, background, fit_cfg = load_fitted(tiny_fitted_run)
    freeze(template)
    sampler = make_sampler(fit_cfg, RunDir(tiny_fitted_run))
    camera = RunDir(tiny_fitted_run).load_cameras().frames[VIEW].resized(40, 40)
    sample = dict(device=None, features=features)
    view = sample_view(camera, template, sampler, background, min_weight=0.0, **sample)
    reference = render_image(camera, template, sampler, background)
    assert torch.allclose(
        view.template_rgb, torch.from_numpy(reference["rgb"]).reshape(-1, 3), atol=1e-5
    )
    assert torch.allclose(
        view.opacity, torch.from_numpy(reference["opacity"]).reshape(-1), atol=1e-5
    )
    # the gate rendered: with g = 1 / 2 everywhere, half the opacity and half the template's
    # colour without the background (the part's share P of I_o)
    region, part = render_gate(view, lambda points: torch.full((len(points),), 0.5))
    assert torch.allclose(region, view.opacity / 2, atol=1e-5)
    on_black = render_image(camera, template, sampler, torch.zeros(3))["rgb"].reshape(-1, 3)
    assert on_black.max() > 0.3 and torch.allclose(part, torch.from_numpy(on_black) / 2, atol=1e-5)
    editing = EditingField(template.grid.cfg, texture_cond=template.cfg.geo_feat_dim * features)
    with torch.no_grad():
        editing.texture.mlp[-1].weight.normal_(0, 0.5)
        for deform in (editing.deform, editing.forward_deform):
            deform.mlp[-1].weight.zero_(), deform.mlp[-1].bias.zero_()
    rendered = render_image(camera, edited_query(template, editing), sampler, background)
    mod = render_modification(view, editing.texture, chunk=100)
    assert mod.abs().max() > 0.01
    assert torch.allclose(mod, torch.from_numpy(rendered["mod"]).reshape(-1, 3), atol=1e-5)
    # pruned samples: fewer queries, nearly the same image
    pruned = sample_view(camera, template, sampler, background, min_weight=1e-2, **sample)
    assert pruned.points.shape[0] < 0.8 * view.points.shape[0]
    assert (render_modification(pruned, editing.texture) - mod).abs().max() < 0.05
    # a crop holds its pixels' samples
    crop = view.crop(10, 30, 5, 25)
    assert crop.size == (20, 20)
    full = mod.reshape(40, 40, 3)[10:30, 5:25].reshape(-1, 3)
    assert torch.allclose(render_modification(crop, editing.texture), full, atol=1e-6)


def test_lifted_region_follows_the_painted_half_and_keeps_the_unseen_side(tiny_fitted_run):
    """The left half of the editing view painted: in that view the lifted mask is the painted
    object pixels and the kept mask (seen, not painted) the other object pixels; from the
    opposite side (surface the editing view never saw) nothing may change and nothing is kept
    for having been seen; the background neither."""
    run = RunDir(tiny_fitted_run)
    template, background, fit_cfg = load_fitted(run.root)
    sampler = make_sampler(fit_cfg, run)
    frames = run.load_cameras().frames
    camera = frames[VIEW]
    region = np.zeros((camera.height, camera.width), bool)
    region[:, : camera.width // 2] = True
    view = sample_view(camera, template, sampler, background)
    lifted = LiftedRegion.from_view(view, region, tol=0.02)
    assert lifted.tol >= 2 * 2.0 / camera.fx  # two pixel footprints at the depth (> 2)
    obj = view.opacity.reshape(64, 64).numpy() > 0.5
    editable = lifted.editable(view).reshape(64, 64).numpy()
    assert editable[obj & region].all() and not editable[obj & ~region].any()
    assert not editable[~obj].any()
    kept = lifted.kept(view).reshape(64, 64).numpy()
    assert kept[obj & ~region].all() and not kept[obj & region].any() and not kept[~obj].any()
    far = sample_view(frames[(VIEW + 4) % len(frames)], template, sampler, background)
    assert lifted.editable(far).float().mean() < 0.05
    assert lifted.kept(far).float().mean() < 0.05


def test_mirrored_painting_reaches_the_side_view_k_does_not_see(tiny_fitted_run):
    """The body painted in view K (the toy car's side, y > 0): across the proxy's mirror plane
    (y = 0) the painting marks the body on the far side, which the opposite view shows and
    view K's own lifted points do not reach; what view K saw unpainted is kept there too. (The
    tiny template's surface lies ~0.05 from its mirror image: a tolerance of 0.1.)"""
    from edit.shape_prior import proxy_mirror_plane

    run = RunDir(tiny_fitted_run)
    template, background, fit_cfg = load_fitted(run.root)
    sampler = make_sampler(fit_cfg, run)
    frames = run.load_cameras().frames
    plane = proxy_mirror_plane(run)
    assert plane is not None and abs(plane[1]) > 0.99  # the car's mirror plane, normal y
    body = read_label_map(tiny_fitted_run / "labels" / frames[VIEW].name) == PART
    lifted = LiftedRegion.from_view(
        sample_view(frames[VIEW], template, sampler, background), body, 0.1
    )
    mirrored = lifted.mirrored(plane)
    assert len(mirrored.points) == 2 * len(lifted.points)
    opposite = (VIEW + len(frames) // 2) % len(frames)
    far = sample_view(frames[opposite], template, sampler, background)
    far_body = (
        read_label_map(tiny_fitted_run / "labels" / frames[opposite].name).reshape(-1) == PART
    )
    far_obj = far.opacity.numpy() > 0.5
    assert lifted.editable(far).float().mean() < 0.02  # view K never saw this side
    editable = mirrored.editable(far).numpy()
    iou = (editable & far_body).sum() / (editable | far_body).sum()
    kept = mirrored.kept(far).numpy()
    assert iou > 0.7, iou
    assert kept[far_obj & ~far_body].mean() > 0.8 and kept[far_body].mean() < 0.2


@pytest.fixture(scope="module")
def features_run(tiny_fitted_run, tmp_path_factory):
    """A copy of the tiny fitted run (no edits) with a tiny feature field."""
    from feature_run_helpers import TINY_FEATURES

    from edit.feature_field_fit import FeaturesConfig, distill_features

    root = tmp_path_factory.mktemp("features") / "run"
    shutil.copytree(tiny_fitted_run, root, ignore=shutil.ignore_patterns("edits"))
    distill_features(root, FeaturesConfig(**TINY_FEATURES), progress=False)
    return root


def test_mirror_agreement_compares_the_masks_with_the_mirrored_painting_on_unseen_surface():
    """View K saw the side x = 1 of a box, painted above z = 0; the mirror plane is x = 0. On
    the far side (x = -1) a mask that follows the mirrored painting agrees fully, one that takes
    the whole side scores the painted share (IoU ~1/2); what view K saw is not compared."""
    grid = np.stack(np.meshgrid(np.linspace(-1, 1, 21), np.linspace(-1, 1, 21)), -1).reshape(-1, 2)
    seen = np.column_stack([np.full(len(grid), 1.0), grid])  # [441, 3] x = 1
    lifted = LiftedRegion(seen, seen[:, 2] > 0, tol=0.05)
    plane = np.array([1.0, 0.0, 0.0, 0.0])
    far = seen * [-1.0, 1.0, 1.0]  # the side x = -1
    above = far[:, 2] > 0
    assert lifted.mirror_agreement(plane, [(far, above)]) == (1.0, len(far))
    iou, n = lifted.mirror_agreement(plane, [(far, np.ones(len(far), bool))])
    assert iou == pytest.approx(above.sum() / len(far)) and n == len(far)
    # view K's own side is not compared (it is what the painting says, not a guess)
    assert lifted.mirror_agreement(plane, [(seen, ~above)])[1] == 0
    assert np.isnan(lifted.mirror_agreement(plane, [(seen, above)])[0])
    # a point of the far side farther than tol from every mirrored point is not compared either
    off = far + [0.0, 0.0, 0.03]  # within tol
    assert lifted.mirror_agreement(
        plane, [(np.vstack([off, [[-1.0, 0.0, 5.0]]]), np.r_[above, True])]
    )[1] == len(far)


def view_k_of(root):
    """(the run, camera -> its ViewSamples through the template, view K's camera, the body's
    GT label [H, W] in view K) of a tiny run."""
    run = RunDir(root)
    template, background, fit_cfg = load_fitted(run.root)
    sampler = make_sampler(fit_cfg, run)
    camera = run.load_cameras().frames[VIEW]
    body = read_label_map(root / "labels" / camera.name) == PART
    return run, lambda cam: sample_view(cam, template, sampler, background), camera, body


def test_symmetric_auto_mirrors_a_painting_the_far_side_masks_follow(features_run):
    """The tiny car's body painted in view K: the semantic masks of the side view K does not see
    agree with its mirror image far better than with the mirror image of a stroke on the body's
    front fifth; at a threshold between the two (the tiny feature field's masks are coarse: the
    body's agreement is ~0.5 here), --symmetric-auto mirrors the body, whose mirror image may then
    change in the opposite view, and not the stroke; --no-symmetric-auto never mirrors."""
    from edit.texture_setup import TextureSetup, editable_masker

    run, sample, camera, body = view_k_of(features_run)
    front = np.arange(camera.width) < np.percentile(np.nonzero(body)[1], 20)
    view = sample(camera)
    frames = run.load_cameras().frames
    opposite = (VIEW + len(frames) // 2) % len(frames)
    far = sample(frames[opposite])
    far_body = read_label_map(features_run / "labels" / frames[opposite].name) == PART
    far_body = far_body.reshape(-1) & (far.opacity.numpy() > 0.5)

    def masker(region, **options):
        setup = TextureSetup(camera, view, None, np.zeros((8, 8, 3), np.float32), region)
        cfg = TextureEditConfig(lift_tol=0.1, symmetric_agreement=0.4, **options)
        masker, _ = editable_masker(run, setup, cfg, torch.device("cpu"))
        return masker, setup.mirror

    body_masker, body_verdict = masker(body)
    _, stroke_verdict = masker(body & front[None, :])
    assert body_verdict["by"] == "auto" and body_verdict["mirrored"], body_verdict
    assert body_verdict["agreement"] > stroke_verdict["agreement"] + 0.15
    assert not stroke_verdict["mirrored"], stroke_verdict
    plain_masker, plain_verdict = masker(body, symmetric_auto=False)
    assert plain_verdict == {"mirrored": False, "by": "--no-symmetric-auto"}
    mirrored, plain = body_masker(far).numpy(), plain_masker(far).numpy()
    # on the far side the mirror takes away what is not the body (the plain masks' excess)
    precision = lambda m: (m & far_body).sum() / m.sum()  # noqa: E731
    recall = lambda m: (m & far_body).sum() / far_body.sum()  # noqa: E731
    assert precision(mirrored) > precision(plain) + 0.2, (precision(mirrored), precision(plain))
    assert recall(mirrored) > 0.8, recall(mirrored)  # here: 0.97 / 0.62, recall 0.88


def test_semantic_masks_keep_what_view_k_saw_unpainted(features_run):
    """The front half of the body painted in view K: the body's semantic mask reaches its
    unpainted half too; with keep_seen that half keeps the template in view K and wherever
    another view sees it, while the far side (never seen by view K) is as without it."""
    from edit.texture_setup import TextureSetup, editable_masker

    run, sample, camera, body = view_k_of(features_run)
    frames = run.load_cameras().frames
    cols = np.nonzero(body)[1]
    region = body & (np.arange(camera.width) < np.median(cols))[None, :]
    view = sample(camera)
    setup = TextureSetup(camera, view, None, np.zeros((8, 8, 3), np.float32), region)
    masks = {}
    for keep in (False, True):
        # features alone: the surface point would already hold the mask to the painted half
        cfg = TextureEditConfig(keep_seen=keep, mask_spatial=0.0, symmetric_auto=False)
        masker, source = editable_masker(run, setup, cfg, torch.device("cpu"))
        assert source == "features"
        masks[keep] = [masker(sample(frames[k])).numpy() for k in (VIEW, (VIEW + 4) % len(frames))]
    (k_off, far_off), (k_on, far_on) = masks[False], masks[True]
    unpainted = (body & ~region).reshape(-1)
    assert k_off[unpainted].mean() > 0.2  # the semantic mask reaches the unpainted half
    assert not k_on[unpainted].any() and not (k_on & ~k_off).any()
    assert k_on[region.reshape(-1)].mean() > 0.8 * k_off[region.reshape(-1)].mean()
    assert np.mean(far_on != far_off) < 0.05 and far_off.sum() > 20


# ---- a tiny texture edit end to end ---------------------------------------------------------


@pytest.fixture(scope="module")
def texture_run(tiny_fitted_run, tmp_path_factory):
    """A copy of the tiny run, a target (view VIEW with the body's hue turned by 120 degrees,
    made with edit/targets.py) and an uninterrupted tiny texture edit "full"."""
    run = tmp_path_factory.mktemp("texture_edit") / "run"
    shutil.copytree(tiny_fitted_run, run)
    scene = load_scene(run, device="cpu")
    camera = RunDir(run).load_cameras().frames[VIEW]
    view = scene.render_view(camera)
    region = read_label_map(run / "labels" / camera.name) == PART
    write_mask(run / "region.png", region)
    image = recolor_region(view["rgb"], region, 120.0)
    write_rgba(run / "target.png", image, view["opacity"], background=scene.background().numpy())
    cfg = TextureEditConfig(**TINY_TEXTURE_EDIT)
    args = (run, VIEW, run / "target.png", "full", cfg)
    metrics = run_texture_edit(*args, region=run / "region.png", progress=False)
    return run, metrics


def test_texture_edit_lowers_its_loss_and_changes_the_part_most(texture_run):
    run, metrics = texture_run
    out = run / "edits" / "full"
    log = json.loads((out / "log.json").read_text())
    assert [e["step"] for e in log] == list(range(1, 31))
    for e in log:  # every term logged and summed into the loss
        assert e["loss"] == pytest.approx(
            sum(e[k] for k in ("reg", "photometric", "cls", "structure", "reg_field")), rel=1e-5
        )
    photo = [e["photometric"] for e in log]
    assert np.mean(photo[-5:]) < 0.6 * np.mean(photo[:5]), photo
    for name in ("edit_field.pt", "region.png", "target.png", "template_view.png", "metrics.json"):
        assert (out / name).is_file(), name
    saved = load_torch(out / "edit_field.pt")
    assert saved["method"] == "texture" and saved["compositor"] is not None
    assert metrics["iterations"] == 30 and metrics["mask_source"] == "lifted"
    frames = RunDir(run).load_cameras().frames
    template, edit = load_scene(run, device="cpu"), load_scene(run, edit="full", device="cpu")
    target = read_image(run / "edits" / "full" / "target.png")
    for k in (VIEW, OTHER):
        part = read_label_map(run / "labels" / frames[k].name) == PART
        before = template.render_view(frames[k])
        after = edit.render_view(frames[k])["rgb"]
        change = np.abs(after - before["rgb"]).sum(-1)
        rest = (before["opacity"] > 0.5) & ~part
        factor = 3 if k == VIEW else 1.5  # OTHER sees part of the body VIEW saw
        assert change[part].mean() > factor * change[rest].mean(), (k, change[part].mean())

        if k == VIEW:  # nearer to the target than the template is, on the part
            assert (
                np.abs(after - target)[part].mean()
                < 0.7 * np.abs(before["rgb"] - target)[part].mean()
            )


@pytest.mark.slow
def test_interrupted_texture_edit_resumes_bit_exactly(texture_run):
    run, _ = texture_run
    cfg = TextureEditConfig(**TINY_TEXTURE_EDIT)
    args = (run, VIEW, run / "target.png", "resumed", cfg)
    kwargs = {"region": run / "region.png", "progress": False}
    assert run_texture_edit(*args, **kwargs, stop_at=10) == {"step": 10}
    assert (run / "edits" / "resumed.partial" / "checkpoint.pt").is_file()
    assert run_texture_edit(*args, **kwargs)["iterations"] == 30
    full = load_torch(run / "edits" / "full" / "edit_field.pt")
    resumed = load_torch(run / "edits" / "resumed" / "edit_field.pt")
    for part in ("editing", "compositor"):
        assert full[part].keys() == resumed[part].keys()
        for k in full[part]:
            assert torch.equal(full[part][k], resumed[part][k]), (part, k)
    assert run_texture_edit(*args, **kwargs)["skipped"]


@pytest.mark.slow
def test_fit_transform_starts_near_the_target_slows_the_per_pixel_parts_and_resumes(
    texture_run,
):
    """The target turns the body's hue (one colour transform): the fitted shared transform is
    kept, so the first step's photometric loss (before any update) is far below the one of an
    edit that starts at no change, and F_dT and the UNet learn at their slowed rates (the shared
    transform at its own). A run resumed after the first step goes on from its checkpoint, not
    from a new fit (bit-exact). A fit whose residual is above --fit-max-residual is undone."""
    run, _ = texture_run
    assert TextureEditConfig().fit_transform  # the default
    cfg = TextureEditConfig(**{**TINY_TEXTURE_EDIT, "fit_transform": True})
    kwargs = {"region": run / "region.png", "progress": False}

    def saved(name: str) -> dict:
        return torch.load(run / "edits" / f"{name}.partial" / "checkpoint.pt", weights_only=True)

    def first_photometric(name: str) -> float:
        return json.loads(saved(name)["log"])[0]["photometric"]

    def rates(name: str) -> dict[str, float]:
        groups = saved(name)["state"]["optimizer"]["state_dict"]["param_groups"]
        return {g["name"]: g["lr"] for g in groups}

    def edit(name: str, cfg: TextureEditConfig, stop: int):
        run_texture_edit(run, VIEW, run / "target.png", name, cfg, **kwargs, stop_at=stop)

    edit("fit_a", cfg, 1)
    edit("no_fit", dataclasses.replace(cfg, fit_transform=False), 1)
    assert first_photometric("fit_a") < 0.5 * first_photometric("no_fit")
    slowed = {k: rates("fit_a")[k] / rates("no_fit")[k] for k in rates("no_fit")}
    f_dt, unet = cfg.fitted_lr_factor, cfg.fitted_compositor_factor
    assert slowed == pytest.approx({"grid": f_dt, "mlp": f_dt, "compositor": unet, "transform": 1})
    edit("fit_a", cfg, 3)
    for stop in (2, 3):  # interrupted after the first step, resumed
        edit("fit_b", cfg, stop)
    a, b = (saved(n)["state"]["compositor"]["state_dict"] for n in ("fit_a", "fit_b"))
    assert all(torch.equal(a[k], b[k]) for k in a)
    assert rates("fit_a") == rates("fit_b")
    edit("undone", dataclasses.replace(cfg, fit_max_residual=0.0), 1)
    assert first_photometric("undone") == pytest.approx(first_photometric("no_fit"), rel=1e-4)
    assert rates("undone") == rates("no_fit")
    for name in ("fit_a", "fit_b", "no_fit", "undone"):
        shutil.rmtree(run / "edits" / f"{name}.partial")


def test_an_edit_of_a_template_fitted_again_is_learnt_again(texture_run, capsys):
    run, _ = texture_run
    args = (run, VIEW, run / "target.png", "full", TextureEditConfig(**TINY_TEXTURE_EDIT))
    kwargs = {"region": run / "region.png", "progress": False}
    assert run_texture_edit(*args, **kwargs)["skipped"]
    path = run / "template" / "field.pt"
    original = path.read_bytes()
    refit = torch.load(path, weights_only=True)
    name = next(iter(refit["field"]))
    refit["field"][name] = refit["field"][name] + 1e-3
    try:
        save_torch(path, refit)
        capsys.readouterr()
        assert run_texture_edit(*args, **kwargs, stop_at=1) == {"step": 1}
        assert "template/field.pt is not the one it was made from" in capsys.readouterr().out
    finally:
        path.write_bytes(original)
        shutil.rmtree(run / "edits" / "full.partial", ignore_errors=True)
    assert run_texture_edit(*args, **kwargs)["skipped"]


def test_texture_baselines_and_scene(texture_run):
    run, _ = texture_run
    camera = RunDir(run).load_cameras().frames[VIEW]
    region = read_mask(run / "region.png")
    target = read_image(run / "edits" / "full" / "target.png")
    variants = (  # the cheap parts only: no DINO
        ("naive", {"method": "naive", "iterations": 40, "lr_naive": 1e-2}),
        ("sum", {"compositor": False, "tex_views": 0, "iterations": 16}),
        ("residual", {"compositor_head": "residual", "tex_views": 0, "iterations": 16}),
    )
    # the default edit's compositor (the affine head) comes back with its head
    full = load_torch(run / "edits" / "full" / "edit_field.pt")["compositor"]
    assert load_scene(run, edit="full", device="cpu").compositor.kind == "affine"
    assert full["head.bias"].numel() == HEADS["affine"]
    for name, change in variants:
        cfg = dataclasses.replace(TextureEditConfig(**TINY_TEXTURE_EDIT), **change)
        run_texture_edit(
            run, VIEW, run / "target.png", name, cfg, region=run / "region.png", progress=False
        )
        saved = load_torch(run / "edits" / name / "edit_field.pt")
        assert saved["method"] == ("naive" if name == "naive" else "texture")
        if name == "residual":  # the scene loads the compositor's head back
            head = load_scene(run, edit=name, device="cpu").compositor.kind
            assert head == name and saved["compositor"]["head.bias"].numel() == HEADS[name]
        else:
            assert name == "naive" or saved["compositor"] is None
        after = load_scene(run, edit=name, device="cpu").render_view(camera)["rgb"]
        before = read_image(run / "edits" / name / "template_view.png")
        assert np.abs(after - target)[region].mean() < np.abs(before - target)[region].mean()
    # strength 0 is the template, exactly the images the compositor blends
    scene = load_scene(run, edit="full", strength=0.0, device="cpu")
    template = load_scene(run, device="cpu").render_view(camera)["rgb"]
    assert np.allclose(scene.render_view(camera)["rgb"], template, atol=1e-5)
    # the compositor acts on each sub-pixel image of one ray per pixel (what it was trained
    # on), the pixel's box filter after it: not the composite of the box-filtered images
    scene = load_scene(run, edit="full", device="cpu")
    assert scene.supersample == 2 and scene.compositor_region and scene.part_colour
    field_query = edited_query(scene.template.field, scene.editing, 1.0)

    def query(points, dirs):
        out = field_query(points, dirs)
        region = scene.editing.gate(points)[:, None]
        return {**out, "region": region, "part": region * out["rgb"]}

    channels = ("rgb", "mod", "region", "part")
    out = render_image(
        camera, query, scene.sampler(), scene.template.background, supersample=2, subpixels=channels
    )

    def composite(images):  # I_o, I_m [H, W, 3], g [H, W, 1], P [H, W, 3] -> I [H, W, 3]
        rgb, mod, region, part = (torch.from_numpy(np.ascontiguousarray(x)) for x in images)
        with torch.no_grad():
            return composite_hwc(scene.compositor, rgb, mod, region[..., 0], part).numpy()

    by_subpixel = [composite([out[f"{k}_subpixels"][i] for k in channels]) for i in range(4)]
    rendered = scene.render_view(camera)["rgb"]
    # plus, where a silhouette crosses the pixel, the template's change from its 4 x 4 rays
    finer = out["rgb"] - out["rgb_subpixels"].mean(axis=0)
    assert np.abs(finer).max() > 1e-3
    np.testing.assert_allclose(rendered, np.mean(by_subpixel, axis=0) + finer, atol=1e-5)
    of_means = composite([out[k] for k in channels])
    assert np.abs(rendered - of_means).max() > 1e-3  # at the part's edges
    # exported colours come from the compositor's images
    vertices, triangles, colours = load_scene(run, edit="full", device="cpu").colored_mesh()
    assert colours.shape == vertices.shape and colours.min() >= 0 and colours.max() <= 1


@pytest.mark.slow
def test_reference_edit_takes_the_photos_colours(texture_run):
    """Unaligned case: the part takes the colours of the photo's opaque pixels (the colour term;
    the transparent pixels' magenta does not count), the rest of the object stays."""
    from edit.texture_loss import sliced_wasserstein

    run, _ = texture_run
    yy, xx = np.mgrid[0:64, 0:64] / 63.0
    disc = (xx - 0.5) ** 2 + (yy - 0.5) ** 2 < 0.16
    green = np.stack([0.1 + 0.1 * xx, 0.5 + 0.2 * yy, 0.1 + 0 * xx], axis=-1)
    photo = np.where(disc[..., None], green, [1.0, 0.0, 1.0]).astype(np.float32)
    write_rgba(run / "photo.png", photo, disc.astype(np.float32))
    cfg = TextureEditConfig(**TINY_TEXTURE_EDIT)
    run_texture_edit(
        run,
        VIEW,
        None,
        "photo",
        cfg,
        region=run / "region.png",
        reference=run / "photo.png",
        progress=False,
    )
    log = json.loads((run / "edits" / "photo" / "log.json").read_text())
    # the colour term is logged every step (0 when a step's view does not see the part)
    assert all("color" in e and "photometric" not in e for e in log)
    assert max(e["color"] for e in log) > 0
    frames = RunDir(run).load_cameras().frames
    template, edit = load_scene(run, device="cpu"), load_scene(run, edit="photo", device="cpu")
    reference = torch.from_numpy(green[disc].astype(np.float32))
    for k in (VIEW, OTHER):
        part = read_label_map(run / "labels" / frames[k].name) == PART
        before = template.render_view(frames[k])
        after = edit.render_view(frames[k])["rgb"]
        before_d, after_d = (
            float(sliced_wasserstein(torch.from_numpy(image[part]), reference, torch.eye(3)))
            for image in (before["rgb"], after)
        )
        closer, factor = (0.5, 3) if k == VIEW else (0.85, 1.5)  # OTHER: part of what VIEW saw
        assert after_d < closer * before_d, (k, after_d, before_d)
        change = np.abs(after - before["rgb"]).sum(-1)
        rest = (before["opacity"] > 0.5) & ~part
        assert change[part].mean() > factor * change[rest].mean(), k


def _disc_photo(backdrop) -> tuple[np.ndarray, np.ndarray]:
    """A 96 px photo without alpha: a green disc (its colours vary) on `backdrop` [3] with a
    little noise -> (photo [96, 96, 3], disc [96, 96] bool)."""
    yy, xx = np.mgrid[0:96, 0:96] / 95.0
    disc = (xx - 0.5) ** 2 + (yy - 0.45) ** 2 < 0.09
    green = np.stack([0.1 + 0.1 * xx, 0.5 + 0.2 * yy, 0.1 + 0 * xx], axis=-1)
    noise = np.random.default_rng(0).normal(0, 0.01, (96, 96, 3))
    photo = np.where(disc[..., None], green, np.asarray(backdrop) + noise)
    return np.clip(photo, 0, 1).astype(np.float32), disc


def test_reference_without_alpha_is_keyed_from_its_backdrop(tmp_path):
    """A photo without alpha on a plain backdrop: its object's colours only, the backdrop
    replaced by the run's background (keyed, or by saliency when asked); `none` keeps every
    pixel; a close-up of a texture (no backdrop to key) keeps every pixel under `auto` too."""
    from edit.texture_setup import read_reference

    photo, disc = _disc_photo([0.55, 0.55, 0.6])
    photo_path = tmp_path / "photo.png"
    write_image(photo_path, photo)
    keyed = read_reference(photo_path, (1.0, 0.0, 1.0))
    assert keyed.pixels == "keyed"
    assert (keyed.colors[:, 1] > 0.45).all()  # green only: not one backdrop pixel
    assert len(keyed.colors) > 0.9 * disc.sum()
    outside = keyed.rgb[~disc]
    assert np.mean(np.all(np.abs(outside - [1.0, 0.0, 1.0]) < 1e-6, axis=1)) > 0.95
    salient = read_reference(photo_path, (1.0, 0.0, 1.0), mask="saliency")
    assert salient.pixels == "saliency" and (salient.colors[:, 1] > 0.45).mean() > 0.95
    every = read_reference(photo_path, (1.0, 0.0, 1.0), mask="none")
    assert every.pixels == "all" and len(every.colors) == photo.shape[0] * photo.shape[1]
    np.testing.assert_allclose(every.rgb, read_image(photo_path))
    texture = np.random.default_rng(1).uniform(0, 1, (96, 96, 3)).astype(np.float32)
    write_image(tmp_path / "texture.png", texture)
    assert read_reference(tmp_path / "texture.png", (1.0, 1.0, 1.0)).pixels == "all"


def test_texture_cli_runs_and_errors_are_one_line(texture_run, capsys):
    run, _ = texture_run
    base = ["edit", str(run), "--view", str(VIEW), "--mode", "texture", "--quiet"]
    tiny = ["--iterations", "2", "--tex-size", "32", "--patch-size", "16", "--previews", "0"]
    target, region = str(run / "target.png"), str(run / "region.png")
    write_rgba(run / "clear.png", np.zeros((8, 8, 3), np.float32), np.zeros((8, 8), np.float32))
    capsys.readouterr()
    assert (
        sine_cli.main(base + ["--target", target, "--region", region, "--name", "cli"] + tiny) == 0
    )
    out = capsys.readouterr().out
    assert "edit cli (texture, ours): 2 steps" in out and "edited part of view" in out
    assert json.loads((run / "edits" / "cli" / "edit.json").read_text())["tex_size"] == 32
    for args, message in (
        (base, "needs --target"),
        (base + ["--target", target, "--mask", region], "--mask is for --mode geometry"),
        (["edit", str(run), "--view", "0", "--reference", target, "--quiet"], "--reference is for"),
        (base + ["--reference", str(run / "nope.png")], "does not exist"),
        (base + ["--reference", str(run / "clear.png")], "fully transparent"),
    ):
        assert sine_cli.main(args) == 2
        err = capsys.readouterr().err.strip()
        assert message in err and "\n" not in err, err


def test_options_of_both_modes_share_their_defaults():
    """`sine edit` adds an option both configs have once: its default must fit both."""
    geometry = {f.name: f for f in dataclasses.fields(GeometryEditConfig)}
    shared = [f for f in dataclasses.fields(TextureEditConfig) if f.name in geometry]
    assert {f.name for f in shared} >= {"method", "iterations", "w_reg", "seed", "previews"}
    for f in shared:
        assert f.default == geometry[f.name].default, f.name
        assert f.metadata.get("choices") == geometry[f.name].metadata.get("choices"), f.name
