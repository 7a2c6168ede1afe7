"""The texture loss L_tex (SINE Sec. 3, after Splice): appearance from the target's DINO CLS token,
structure from the template render's key self-similarity.

L_tex = ||cls(I_t) - cls(I)||_2 + ||S(I_o) - S(I)||_F, with I_t the edited target image, I_o the
template render of a view and I the edited render of the same view; S is the cosine
self-similarity of the last block's keys. Averaged over the batch of views.

`sliced_wasserstein` (beyond the paper, for reference photos): how far the colours of a set of
pixels are from a reference's colour distribution, as the squared sliced 2-Wasserstein distance
(Rabin et al. 2011; as used for texture synthesis by Heitz et al. 2021).
"""

from __future__ import annotations

import torch
from torch import nn

from edit.dino import Dino


class TextureLoss(nn.Module):
    """L_tex against one target image; cls(I_t) is computed once and cached (no graph)."""

    def __init__(
        self,
        dino: Dino,
        target_image: torch.Tensor,
        cls_weight: float = 1.0,
        structure_weight: float = 1.0,
    ):
        """target_image: [3, H, W] or [1, 3, H, W] RGB in [0, 1]."""
        super().__init__()
        self.dino = dino
        self.cls_weight = cls_weight
        self.structure_weight = structure_weight
        if target_image.dim() == 3:
            target_image = target_image[None]
        with torch.no_grad():
            target_cls = dino.cls(target_image)  # [1, D]
        self.register_buffer("target_cls", target_cls, persistent=False)

    @torch.no_grad()
    def template_similarity(self, template: torch.Tensor) -> torch.Tensor:
        """S(I_o) [B, T, T] of template renders [B, 3, H, W]: cache it per fixed view."""
        return self.dino.self_similarity(self.dino.keys(template))

    def terms(
        self,
        image: torch.Tensor,
        template: torch.Tensor | None = None,
        template_sim: torch.Tensor | None = None,
    ) -> dict[str, torch.Tensor]:
        """The two terms (batch means) for edited renders `image` [B, 3, H, W] in [0, 1].

        Give either the template renders of the same views (`template`, same size) or their
        cached `template_similarity`. One DINO pass over `image`, differentiable.
        """
        if template_sim is None:
            if template is None:
                raise ValueError("give the template render or its cached similarity")
            if template.shape != image.shape:
                raise ValueError(f"template {tuple(template.shape)} vs image {tuple(image.shape)}")
            template_sim = self.template_similarity(template)
        out = self.dino(image)
        sim = self.dino.self_similarity(out.keys)  # [B, T, T]
        if sim.shape != template_sim.shape:
            raise ValueError(
                f"similarity {tuple(sim.shape)} vs template {tuple(template_sim.shape)}"
            )
        cls_term = torch.linalg.vector_norm(out.cls - self.target_cls, dim=-1).mean()
        structure = torch.linalg.matrix_norm(sim - template_sim).mean()  # Frobenius
        return {"cls": cls_term, "structure": structure}

    def forward(
        self,
        image: torch.Tensor,
        template: torch.Tensor | None = None,
        template_sim: torch.Tensor | None = None,
    ) -> torch.Tensor:
        """Scalar L_tex = cls_weight * cls term + structure_weight * structure term."""
        t = self.terms(image, template, template_sim)
        return self.cls_weight * t["cls"] + self.structure_weight * t["structure"]


def sliced_wasserstein(
    colours: torch.Tensor, reference: torch.Tensor, directions: torch.Tensor
) -> torch.Tensor:
    """Squared sliced 2-Wasserstein distance between the colour sets `colours` [N, C] and
    `reference` [M, C] along unit `directions` [K, C]: both sets are projected on each direction,
    sorted, and the i-th smallest projection of `colours` is compared with the reference's
    quantile at level (i + 0.5) / N (linear interpolation); the mean squared difference over
    i and the directions. Gradients reach `colours` only. 0 when both sets hold the same
    colours in the same proportions."""
    if len(colours) == 0 or len(reference) == 0:
        return colours.sum() * 0
    ours = (colours @ directions.T).sort(dim=0).values  # [N, K]
    with torch.no_grad():
        theirs = (reference @ directions.T).sort(dim=0).values  # [M, K]
        n, m = len(colours), len(reference)
        level = (torch.arange(n, device=colours.device, dtype=colours.dtype) + 0.5) / n
        pos = level * m - 0.5  # the quantile's position among the sorted reference values
        lo = pos.floor().clamp(0, m - 1)
        frac = (pos - lo).clamp(0, 1)[:, None]
        lo = lo.long()
        hi = (lo + 1).clamp(max=m - 1)
        quantiles = theirs[lo] * (1 - frac) + theirs[hi] * frac  # [N, K]
    return (ours - quantiles).pow(2).mean()
