"""Deferred back-propagation (ARF, Zhang et al. 2022; DESIGN.md section 2): image-space losses on
full rendered images with the memory of one piece of an image.

A loss on a whole image (DINO's L_tex) needs every pixel at once; back-propagating it through the
field directly keeps the graph of every ray's samples alive (memory grows with the resolution).
Instead:

1. render every image without a graph, piece by piece (chunks of rays, or tiles of pixels);
2. make the images leaves that require grad, compute the loss on them and back-propagate: this
   caches d loss / d pixels (and whatever else the loss uses with a graph gets its gradient);
3. re-render the same pieces with a graph and call
   `torch.autograd.backward(piece_channels, cached_grad[piece])`: the parameters accumulate
   exactly the gradients a direct back-propagation would give (the chain rule, split over
   pixels), while only one piece's graph exists at a time.

Pieces are chunks of rays (`ray_chunks`: a pixel depends on its own ray only) or tiles of an image
with a halo (`image_tiles`: a pixel of a 2D network's output depends on its receptive field, so
each tile is computed with `halo` extra pixels around it and only its core is kept; exact when
the halo covers the receptive field, as for `edit.compositor.Compositor` with even tiles and a
halo of 8). Rendering must be deterministic: the same piece gives the same pixels both times.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import torch

LossFn = Callable[[list[dict[str, torch.Tensor]]], tuple[torch.Tensor, Any]]


@dataclass
class DeferredImage:
    """One image in pieces. `render(piece)` gives the piece's channels {name: [*piece, C]} (with
    a graph when grad is enabled); `place(piece)` indexes the piece in the full image, whose
    channels have the leading shape `shape` ((N,) for rays, (H, W) for pixels)."""

    render: Callable[[Any], dict[str, torch.Tensor]]
    pieces: Sequence[Any]
    shape: tuple[int, ...]
    place: Callable[[Any], Any]


def ray_chunks(
    render: Callable[[int, int], dict[str, torch.Tensor]], n_rays: int, chunk: int
) -> DeferredImage:
    """Rays 0..n_rays-1 in chunks; `render(start, stop)` -> {name: [stop - start, C]}."""
    pieces = [(a, min(a + chunk, n_rays)) for a in range(0, n_rays, chunk)]
    return DeferredImage(lambda p: render(*p), pieces, (n_rays,), lambda p: slice(*p))


def image_tiles(
    render: Callable[[int, int, int, int], dict[str, torch.Tensor]],
    height: int,
    width: int,
    tile: int,
    halo: int,
) -> DeferredImage:
    """An image in tiles of `tile` px; `render(y0, y1, x0, x1)` -> {name: [y1 - y0, x1 - x0, C]}
    is called on each tile grown by `halo` px (clipped to the image) and cropped to the tile.
    Tile corners and halo boxes start at multiples of 2 when `tile` and `halo` are even."""
    pieces = []
    for y0 in range(0, height, tile):
        for x0 in range(0, width, tile):
            core = (y0, min(y0 + tile, height), x0, min(x0 + tile, width))
            box = (max(0, y0 - halo), min(height, core[1] + halo))
            box += (max(0, x0 - halo), min(width, core[3] + halo))
            pieces.append((core, box))

    def render_piece(piece):
        (y0, y1, x0, x1), (by0, _, bx0, _) = piece
        out = render(*piece[1])
        return {k: v[y0 - by0 : y1 - by0, x0 - bx0 : x1 - bx0] for k, v in out.items()}

    def place(piece):
        y0, y1, x0, x1 = piece[0]
        return (slice(y0, y1), slice(x0, x1))

    return DeferredImage(render_piece, pieces, (height, width), place)


def assemble(image: DeferredImage) -> dict[str, torch.Tensor]:
    """Every piece rendered (a graph only if grad is enabled) into full channels {name: [*shape,
    C]}."""
    full: dict[str, torch.Tensor] = {}
    for piece in image.pieces:
        for name, value in image.render(piece).items():
            if name not in full:
                lead = len(image.shape)
                full[name] = value.new_zeros(*image.shape, *value.shape[lead:])
            full[name][image.place(piece)] = value
    return full


def deferred_backward(images: Sequence[DeferredImage], loss_fn: LossFn) -> tuple[torch.Tensor, Any]:
    """Accumulates d loss / d parameters into `.grad` (see the module doc); returns the detached
    loss and what `loss_fn` returned besides it. Peak memory: the images, the loss's own graph
    and one piece's graph."""
    leaves = []
    for image in images:
        with torch.no_grad():
            full = assemble(image)
        leaves.append({k: v.requires_grad_(True) for k, v in full.items()})
    loss, extra = loss_fn(leaves)
    loss.backward()
    for image, leaf in zip(images, leaves, strict=True):
        wanted = {k: v.grad for k, v in leaf.items() if v.grad is not None}
        if not wanted:
            continue
        for piece in image.pieces:
            out = image.render(piece)
            where = image.place(piece)
            pairs = [(out[k], g[where]) for k, g in wanted.items() if out[k].requires_grad]
            if pairs:
                torch.autograd.backward([p[0] for p in pairs], [p[1] for p in pairs])
    return loss.detach(), extra


def direct_backward(images: Sequence[DeferredImage], loss_fn: LossFn) -> tuple[torch.Tensor, Any]:
    """The reference: every image assembled with its graph, then one backward."""
    loss, extra = loss_fn([assemble(image) for image in images])
    loss.backward()
    return loss.detach(), extra
