"""Deferred back-propagation (ARF, Zhang et al. 2022; DESIGN.md section 2): image-space losses on
full rendered images with the memory of one chunk of rays.

A loss on a whole image (DINO's L_tex, a CNN compositor) needs every pixel at once; back-propagating
it through the field directly keeps the graph of every ray's samples alive (memory grows with the
resolution). Instead:

1. render every image without a graph, chunk by chunk;
2. make the images leaves that require grad, compute the loss on them (whatever else the loss
   uses with a graph, e.g. the compositor's weights, gets its gradient here directly) and
   back-propagate: this caches d loss / d pixels;
3. re-render the same rays chunk by chunk with a graph and call
   `torch.autograd.backward(chunk_channels, cached_grad[chunk])`: the field's parameters
   accumulate exactly the gradients a direct back-propagation would give (the chain rule, split
   over pixels), while only one chunk's graph exists at a time.

Rendering must be deterministic (the same rays, samples and field give the same pixels both
times) for the cached gradient to belong to the re-rendered pixels.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch

# rays [start, stop) of one image -> channels {name: [stop - start, C]} (with a graph when enabled)
RenderFn = Callable[[int, int], dict[str, torch.Tensor]]
# the images' channels {name: [N, C]}, one dict per image -> (scalar loss, anything else)
LossFn = Callable[[list[dict[str, torch.Tensor]]], tuple[torch.Tensor, object]]


@dataclass
class DeferredImage:
    """One image to render: `render(start, stop)` gives the channels of rays start..stop-1."""

    render: RenderFn
    n_rays: int


def _chunks(n: int, chunk: int):
    for start in range(0, n, chunk):
        yield start, min(start + chunk, n)


def render_full(image: DeferredImage, chunk: int) -> dict[str, torch.Tensor]:
    """All rays of an image without a graph: {name: [n_rays, C]} (detached)."""
    parts: dict[str, list[torch.Tensor]] = {}
    with torch.no_grad():
        for start, stop in _chunks(image.n_rays, chunk):
            for name, value in image.render(start, stop).items():
                parts.setdefault(name, []).append(value.detach())
    return {name: torch.cat(values) for name, values in parts.items()}


def deferred_backward(
    images: Sequence[DeferredImage], loss_fn: LossFn, chunk: int = 4096
) -> tuple[torch.Tensor, object]:
    """Accumulates d loss / d parameters into `.grad` (see the module doc); returns the detached
    loss and what `loss_fn` returned besides it. Peak memory: the images, the loss's own graph
    and one chunk of rays."""
    leaves = []
    for image in images:
        full = render_full(image, chunk)
        leaves.append({k: v.requires_grad_(True) for k, v in full.items()})
    loss, extra = loss_fn(leaves)
    loss.backward()
    for image, leaf in zip(images, leaves, strict=True):
        wanted = {k: v.grad for k, v in leaf.items() if v.grad is not None}
        if not wanted:
            continue
        for start, stop in _chunks(image.n_rays, chunk):
            out = image.render(start, stop)
            pairs = [(out[k], g[start:stop]) for k, g in wanted.items() if out[k].requires_grad]
            if pairs:
                torch.autograd.backward([p[0] for p in pairs], [p[1] for p in pairs])
    return loss.detach(), extra


def direct_backward(
    images: Sequence[DeferredImage], loss_fn: LossFn
) -> tuple[torch.Tensor, object]:
    """The reference: every image rendered in one piece with a graph, then one backward."""
    full = [image.render(0, image.n_rays) for image in images]
    loss, extra = loss_fn(full)
    loss.backward()
    return loss.detach(), extra
