"""Volume-rendering quadrature against hand-computed values; SH basis sanity."""

import math

import torch

from render import volume
from render.sh import sh_encode


def test_deltas_alpha_transmittance_weights_by_hand():
    t = torch.tensor([[1.0, 1.5, 2.5]])
    sigma = torch.tensor([[0.0, math.log(2) / 1.0, 1e6]])  # delta = .5, 1, far
    d = volume.deltas(t, far_delta=1e10)
    torch.testing.assert_close(d, torch.tensor([[0.5, 1.0, 1e10]]))
    a = volume.alphas(sigma, d)
    torch.testing.assert_close(a, torch.tensor([[0.0, 0.5, 1.0]]))
    T = volume.transmittance(a)
    torch.testing.assert_close(T, torch.tensor([[1.0, 1.0, 0.5]]), atol=1e-6, rtol=0)
    w = volume.render_weights(sigma, t)
    torch.testing.assert_close(w, torch.tensor([[0.0, 0.5, 0.5]]), atol=1e-6, rtol=0)
    torch.testing.assert_close(volume.opacity(w), torch.tensor([1.0]), atol=1e-6, rtol=0)
    # depth: 0.5 * 1.5 + 0.5 * 2.5 = 2.0
    torch.testing.assert_close(volume.expected_depth(w, t), torch.tensor([2.0]), atol=1e-5, rtol=0)


def test_two_half_opaque_samples():
    # alpha = 0.5, 0.5 -> weights 0.5, 0.25; opacity 0.75
    alpha = torch.tensor([[0.5, 0.5]])
    w = volume.weights_from_alpha(alpha)
    torch.testing.assert_close(w, torch.tensor([[0.5, 0.25]]), atol=1e-6, rtol=0)


def test_composite_dual_channels_and_background():
    w = torch.tensor([[0.5, 0.25], [0.0, 0.0]])
    red = torch.tensor([1.0, 0.0, 0.0]).expand(2, 2, 3)
    green = torch.tensor([0.0, 1.0, 0.0]).expand(2, 2, 3)
    feat = torch.arange(2 * 2 * 4, dtype=torch.float32).view(2, 2, 4)
    out = volume.composite(w, {"rgb": red, "rgb_edit": green, "feat": feat})
    torch.testing.assert_close(out["rgb"][0], torch.tensor([0.75, 0.0, 0.0]))
    torch.testing.assert_close(out["rgb_edit"][0], torch.tensor([0.0, 0.75, 0.0]))
    torch.testing.assert_close(out["feat"][0], 0.5 * feat[0, 0] + 0.25 * feat[0, 1])
    torch.testing.assert_close(out["feat"][1], torch.zeros(4))
    acc = volume.opacity(w)
    bg = torch.tensor([1.0, 1.0, 1.0])
    rgb = volume.over_background(out["rgb"], acc, bg)
    torch.testing.assert_close(rgb[0], torch.tensor([1.0, 0.25, 0.25]))
    torch.testing.assert_close(rgb[1], bg)


def test_weights_gradient_flows_to_sigma():
    sigma = torch.tensor([[1.0, 2.0, 3.0]], requires_grad=True)
    t = torch.tensor([[0.0, 0.1, 0.2]])
    volume.opacity(volume.render_weights(sigma, t, far_delta=0.1)).sum().backward()
    assert torch.all(sigma.grad > 0)


def test_sh_orthonormal_on_sphere():
    torch.manual_seed(0)
    d = torch.nn.functional.normalize(torch.randn(200000, 3, dtype=torch.float64), dim=-1)
    y = sh_encode(d)
    assert y.shape == (200000, 16)
    gram = 4 * math.pi * (y.T @ y) / d.shape[0]  # Monte Carlo integral over the sphere
    torch.testing.assert_close(gram, torch.eye(16, dtype=torch.float64), atol=0.03, rtol=0)
    # l=1 band: Y_1^0 = sqrt(3/(4 pi)) z
    torch.testing.assert_close(y[:, 2], math.sqrt(3 / (4 * math.pi)) * d[:, 2])
