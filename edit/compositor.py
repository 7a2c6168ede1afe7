"""The colour compositing layer of texture edits (paper Sec. 3.3 + supplementary).

A small 2D UNet blends the template image I_o and the modification image I_m (both rendered with
the same weights, `edit.editing_field.edited_query`) into the edited view I:

    input concat(I_o, I_m)            [B, 6, H, W]
    encoder  conv3x3 6 -> 16, ReLU    e1 [B, 16, H, W]
             conv3x3 16 -> 32 stride 2, ReLU
                                      e2 [B, 32, H/2, W/2]
    decoder  upsample x2 (bilinear, cropped to H, W), conv3x3 32 -> 16, ReLU
             concat with e1 (skip), conv3x3 32 -> 16, ReLU
             conv3x3 16 -> 3 (the head; 12 with the affine head below)
    output   I = sigmoid(logit(clamp(I_o + I_m, eps, 1 - eps)) + g * head)
             g in [0, 1] per pixel: where the edit may act (below)

The head predicts a residual in logit space on top of the plain sum I_o + I_m (which is what the
`--no-compositor` baseline renders). The head starts at zero, so before training the composite is
exactly clamp(I_o + I_m) (up to the eps clamp), and with m' = 0 (F_dT's start) it is I_o: editing
starts at the template. The sum in the base keeps F_dT's colours on a direct path to the image
from the first step (with a zero head nothing else would reach them); the UNet then learns the
blending the per-point field cannot (a colour mapping shared by all views, view-dependent looks).
The gate g confines it to the edited part, so the compositor cannot turn into a global recolouring
of the object (without a gate, it learns the edited part's colour change as a colour transform of
every pixel within a few dozen steps). Texture edits give g as an image: the edited part's 3D
region (`edit.edit_gate.EditGate`, from the semantic masks of every training view) rendered into
the view, so the UNet's colour mapping reaches every side of the part, seen in view K or not.
Without one, g comes from the modification itself, g = 1 - exp(-(|I_m|_1 / TAU)^2): a pixel
with I_m = 0 stays I_o (squared, so faint colours F_dT leaks elsewhere, |I_m|_1 of a few 1e-3,
open it by less than 1 %). The output is a sigmoid, in (0, 1).

Head `affine` (beyond the paper; texture edits' default, `--compositor-head residual` for the
paper's): the head predicts, per pixel, a 3 x 3 matrix A and an offset b (12 channels), and

    I = clamp(base + g * (A base + b), 0, 1)      base = I_o + I_m

(the clamp passes gradients through as if absent, so a pixel pushed out of range is pulled back).
Texture edits with a gate give the part's own colour too: P = sum_s w_s g(x_s) c_s, the share
of the pixel's template colour that comes from the edited part's samples, and then

    I = clamp(base + A (P + I_m) + g * b, 0, 1)

A pixel on the part's rim mixes the part with what lies next to it (the background, another
part); only the part's share is transformed, so where g = 1/2 and P = p/2 the pixel changes by
(A p + b) / 2: half of a part pixel's change, the rest left alone (`--part-colour`; toycar
rims' squared error -12 % and -7 % on two seeds, bench/HISTORY.md). Inside the part (g = 1,
P = I_o) both forms agree.
The UNet says which colour transform applies where; the transform acts on each pixel's colour
linearly. A surface's pixel is its albedo times its shading, so a linear change of the albedo
(a hue rotation, desaturating, painting one colour over a part's shades) is one A for every
shade: the transform learnt on view K carries to shades it did not show (a lit top, a shadowed
side) and passes the template's detail through. The head's bias is the transform every pixel
shares (the texture edit gives it its own learning rate, `--lr-transform`); the UNet's
per-pixel output adds what differs from pixel to pixel. Starts at zero as well: I = base.

The shared transform may have a quadratic term (`quadratic=True`): Q [3, 6] on the products
c_i c_j of the part's own colour c = (P + I_m) / g (clamped to [0, 1]), weighed by g like b:

    I = clamp(base + A (P + I_m) + g * (b + Q quad(c)), 0, 1)

Not every recolouring is linear in RGB: a hue turn that also lifts greys to some saturation
(`recon.mesh_data.recolor_albedo`, the synthetic edits) turns white to pink and yellow to teal
with one rule that no single A makes. Fitted on one view, the quadratic map carries to the
part's held-out pixels closer than the linear one (figurine: 31.9 against 28.8 dB on the part's
pixels, `bench/bench_colour_map.py`).

Every layer is a 3x3 convolution, a x2 down- or up-sampling: the network commutes with shifts of
the image by an even number of pixels and each output pixel depends on input pixels at most 7
away, so `edit.deferred.image_tiles` (even tiles, halo 8) computes it tile by tile exactly.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

EPS = 1e-4  # the base image is clamped to [EPS, 1 - EPS] before the logit
TAU = 0.05  # |I_m|_1 at which the gate g reaches 1 - 1/e
HALO = 8  # pixels around a tile that cover the receptive field (see the module doc)


def _conv(c_in: int, c_out: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(c_in, c_out, 3, stride=stride, padding=1)


HEADS = {"residual": 3, "affine": 12}  # the head's output channels per kind (module doc)
PAIRS = ((0, 0), (1, 1), (2, 2), (0, 1), (0, 2), (1, 2))  # the quadratic term's products


def quadratic_features(colour: torch.Tensor, gate: torch.Tensor) -> torch.Tensor:
    """The quadratic term's inputs: `colour` [N, 3] or [B, 3, H, W] (the part's share of the
    pixel, P + I_m, or the whole base), `gate` [N, 1] or [B, 1, H, W] (g, the part's share of
    the pixel) -> g c_i c_j for the 6 products of c = colour / g, the part's own colour clamped
    to [0, 1] ([N, 6] or [B, 6, H, W]): like the linear term, a rim pixel's change scales with
    the part's share."""
    own = (colour / gate.clamp_min(1e-3)).clamp(0.0, 1.0)
    return gate * torch.stack([own[:, i] * own[:, j] for i, j in PAIRS], dim=1)


class Compositor(nn.Module):
    """(I_o [B, 3, H, W], I_m [B, 3, H, W]) -> I [B, 3, H, W] in (0, 1) (affine: [0, 1]); see
    the module doc. `head`: "residual" (the paper's: a logit residual) or "affine" (a colour
    transform per pixel)."""

    def __init__(self, width: int = 16, head: str = "residual", quadratic: bool = False):
        super().__init__()
        if head not in HEADS:
            raise ValueError(f"unknown compositor head {head!r}; use {' or '.join(HEADS)}")
        if quadratic and head != "affine":
            raise ValueError("only the affine head has a quadratic colour term")
        self.kind = head
        self.enc1 = _conv(6, width)
        self.enc2 = _conv(width, 2 * width, stride=2)
        self.dec2 = _conv(2 * width, width)
        self.dec1 = _conv(2 * width, width)
        self.head = _conv(width, HEADS[head])
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)
        # the shared transform's quadratic term Q [3, 6] (module doc), None: linear only
        self.quadratic = nn.Parameter(torch.zeros(3, len(PAIRS))) if quadratic else None

    @classmethod
    def for_state(cls, state: dict) -> Compositor:
        """An untrained compositor of the shape a `state_dict` was saved from (width, head)."""
        kinds = {n: k for k, n in HEADS.items()}
        return cls(
            width=int(state["enc1.weight"].shape[0]),
            head=kinds[state["head.bias"].numel()],
            quadratic="quadratic" in state,
        )

    def head_output(self, template: torch.Tensor, modification: torch.Tensor) -> torch.Tensor:
        """The head's output [B, 3 or 12, H, W] (zero before training)."""
        e1 = F.relu(self.enc1(torch.cat([template, modification], dim=1)))
        e2 = F.relu(self.enc2(e1))
        up = F.interpolate(e2, scale_factor=2.0, mode="bilinear", align_corners=False)
        up = up[..., : e1.shape[-2], : e1.shape[-1]]  # odd sizes: one row / column more
        d2 = F.relu(self.dec2(up))
        d1 = F.relu(self.dec1(torch.cat([d2, e1], dim=1)))
        return self.head(d1)

    def forward(
        self,
        template: torch.Tensor,
        modification: torch.Tensor,
        region: torch.Tensor | None = None,
        part: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """I_o, I_m [B, 3, H, W]; `region` [B, 1, H, W] in [0, 1]: the gate g itself (the edited
        part's 3D region rendered into the view); None: g from I_m (see the module doc).
        `part` [B, 3, H, W]: the part's share P of I_o; the affine head then transforms P + I_m
        only (module doc); None: the whole base."""
        if template.shape != modification.shape or template.dim() != 4 or template.shape[1] != 3:
            raise ValueError(
                f"expected two [B, 3, H, W] images, got {tuple(template.shape)} and "
                f"{tuple(modification.shape)}"
            )
        base = (template + modification).clamp(EPS, 1.0 - EPS)  # [B, 3, H, W]
        head = self.head_output(template, modification)
        if region is None:
            presence = modification.abs().sum(dim=1, keepdim=True) / TAU  # [B, 1, H, W]
            gate = 1.0 - torch.exp(-(presence**2))
        else:
            gate = region
        if self.kind == "residual":
            return torch.sigmoid(torch.logit(base) + gate * head)
        a = head[:, :9].unflatten(1, (3, 3))  # [B, 3, 3, H, W]
        if part is None:
            own = gate * base  # [B, 3, H, W] the whole pixel, weighed by g
            out = base + gate * (torch.einsum("bijhw,bjhw->bihw", a, base) + head[:, 9:])
        else:
            own = part + modification  # [B, 3, H, W] the part's colour in the pixel
            out = base + torch.einsum("bijhw,bjhw->bihw", a, own) + gate * head[:, 9:]
        if self.quadratic is not None:
            quad = quadratic_features(own, gate)  # [B, 6, H, W]
            out = out + torch.einsum("ik,bkhw->bihw", self.quadratic, quad)
        return out + (out.clamp(0.0, 1.0) - out).detach()  # clamped, gradients as if not


@torch.no_grad()
def fit_shared_transform(
    compositor: Compositor,
    template: torch.Tensor,
    target: torch.Tensor,
    gate: torch.Tensor,
    part: torch.Tensor | None = None,
    ridge: float = 1e-3,
) -> torch.Tensor:
    """Starts the affine head's shared transform (its bias: A, b) at the least-squares colour
    transform that takes the template's pixels to the target's: I_o [N, 3] -> target [N, 3],
    g [N] the gate at each pixel, P [N, 3] the part's share of I_o (None: the whole pixel), with
    I_m = 0 as at the start of an edit (see the module doc: target - I_o = A P + g b, or
    g (A I_o + b)). `ridge` pulls towards no change where the pixels leave it undetermined (a
    part of one colour fixes A only along that colour). -> the residual [N, 3] after the fit."""
    if compositor.kind != "affine":
        raise ValueError("only the affine head has a shared colour transform")
    g = gate.reshape(-1, 1)
    colour = part if part is not None else g * template  # [N, 3]
    columns = [colour, g]
    if compositor.quadratic is not None:
        columns.append(quadratic_features(colour, g))
    x = torch.cat(columns, dim=1).double()  # [N, 4 or 10]
    y = (target - template).double()  # [N, 3]
    gram = x.T @ x + ridge * len(x) * torch.eye(x.shape[1], dtype=x.dtype, device=x.device)
    w = torch.linalg.solve(gram, x.T @ y)  # [4 or 10, 3]: y = x w
    bias = compositor.head.bias
    bias[:9] = w[:3].T.reshape(9).to(bias)  # A[i, j] = w[j, i]
    bias[9:] = w[3].to(bias)
    if compositor.quadratic is not None:
        compositor.quadratic.copy_(w[4:].T.to(bias))
    return (y - x @ w).to(template)


def composite_hwc(
    compositor: Compositor | None, template, modification, region=None, part=None
) -> torch.Tensor:
    """Images [H, W, 3] (torch; `region` [H, W], `part` [H, W, 3] or None) -> the edited image
    [H, W, 3]; no compositor: the plain sum, clamped (the `--no-compositor` rendering,
    `edit.editing_field.combine`)."""
    if compositor is None:
        return (template + modification).clamp(0.0, 1.0)
    gate = None if region is None else region.reshape(1, 1, *region.shape[:2])
    part = None if part is None else part.permute(2, 0, 1)[None]
    chw = compositor(
        template.permute(2, 0, 1)[None], modification.permute(2, 0, 1)[None], gate, part
    )
    return chw[0].permute(1, 2, 0)
