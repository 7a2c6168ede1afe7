"""Texture editing: the compositor, deferred back-propagation against direct back-propagation, the
coarse-to-fine window, the kept template samples against the renderer, the proxy-lifted masks,
and a tiny end-to-end texture edit (its loss falls, colours change in the painted part more than
elsewhere, resume, baselines, the CLI and the edit's scene)."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from edit.compositor import EPS, Compositor, composite_hwc
from edit.deferred import assemble, deferred_backward, direct_backward, image_tiles, ray_chunks
from edit.texture_edit import edited_image
from edit.texture_field import TextureField, cosine_window
from edit.texture_views import (
    ViewSamples,
    render_modification,
)
from render.cameras import Camera, look_at
from render.hashgrid import HashGridConfig
from render.renderer import render_rays
from render.sampler import UniformSampler
from render.template_field import TemplateField, TemplateFieldConfig

SMALL_GRID = HashGridConfig(n_levels=4, log2_table=8, max_resolution=32)


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
    out = comp(template, torch.randn_like(template))
    assert out.min() > 0 and out.max() < 1 and not torch.allclose(out, template, atol=1e-2)
    with pytest.raises(ValueError, match="two"):
        comp(template, template[:, :2])


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
def _random_view(h: int, w: int, seed: int) -> ViewSamples:
    """A synthetic view: 0-3 samples per pixel at random points with random weights."""
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
        points=torch.rand(n, 3, generator=g) * 1.6 - 0.8,
        weights=torch.rand(n, generator=g) * 0.5,
        pixel=torch.repeat_interleave(torch.arange(h * w), counts),
        offsets=offsets,
    )


def _grads(*modules) -> list[torch.Tensor]:
    return [p.grad.clone() for m in modules for p in m.parameters() if p.requires_grad]


def test_deferred_gradients_equal_direct_backpropagation():
    """Two images through F_dT and the compositor, an image-space loss mixing all pixels: the
    parameter gradients of deferred back-propagation in tiles of 4 px (halo 8, F_dT on 5
    samples at a time) equal those of direct back-propagation through the whole images at once."""
    torch.manual_seed(0)
    texture, comp = TextureField(SMALL_GRID), Compositor()
    with torch.no_grad():  # leave the zero start so every parameter gets a gradient
        texture.mlp[-1].weight.normal_(0, 0.5)
        comp.head.weight.normal_(0, 0.5)
    views = [_random_view(14, 11, 1), _random_view(9, 16, 2)]
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
        images.append({"rgb": composite_hwc(comp, view.template_rgb.reshape(h, w, 3), mod)})
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
