"""Losses of geometric editing (paper Sec. 3.2 + supplementary; DESIGN.md section 7).

L_geo = w_gp L_gp + L_gt + w_gr L_gr + w_cyc L_cyc (+ w_reg L_reg), the paper's weights being
w_gp = 0.03, w_gr = 0.1, w_cyc = 10. Every term here is a plain function of tensors so each can be
tested on hand-made inputs; `edit.geometry_edit` samples the points and rays and sums them.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F

from edit.deformation import DeformationField


def photometric(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean over rays of ||C(r) - C_t(r)||^2: pred, target [R, 3] -> scalar."""
    return ((pred - target) ** 2).sum(dim=-1).mean()


def silhouette_bce(opacity: torch.Tensor, silhouette: torch.Tensor) -> torch.Tensor:
    """BCE(O(r), O_e(r)): opacity [R] in [0, 1], target silhouette [R] in {0, 1} -> scalar."""
    return F.binary_cross_entropy(opacity.clamp(1e-5, 1 - 1e-5), silhouette)


def deformation_smoothness(
    deform: DeformationField, points: torch.Tensor, jitter: torch.Tensor
) -> torch.Tensor:
    """L_gr = mean ||grad F_dG(p)|| + ||F_dG(p) - F_dG(p + eps)||_1 at points [M, 3], eps [M, 3].

    Both terms are on the displacement MLP(PE(x)): the identity part of x + MLP is not penalised
    (a translation is perfectly smooth; on the whole map the difference term would pull
    F_dG(p + eps) towards F_dG(p), i.e. collapse space).
    """
    grad = deform.jacobian_norm(points).mean()
    disp = deform.displacement
    diff = (disp(points) - disp(points + jitter)).abs().sum(dim=-1).mean()
    return grad + diff


def cycle(
    deform: DeformationField, forward: DeformationField, points: torch.Tensor
) -> torch.Tensor:
    """L_cyc = mean ||F_dG(F'_dG(p)) - p|| + ||F'_dG(F_dG(p)) - p|| over points [M, 3]."""
    there_back = deform(forward(points)) - points
    back_there = forward(deform(points)) - points
    return there_back.norm(dim=-1).mean() + back_there.norm(dim=-1).mean()


def chamfer(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Two-way Chamfer as in the paper's L_gp: sum_a min_b ||a - b||^2 + sum_b min_a ||a - b||^2,
    a [N, 3], b [M, 3] -> scalar (a sum, so it grows with the point counts: sample fixed counts)."""
    d2 = torch.cdist(a, b) ** 2  # [N, M]
    return d2.min(dim=1).values.sum() + d2.min(dim=0).values.sum()


def displacement_l1(deform: DeformationField, points: torch.Tensor) -> torch.Tensor:
    """L_reg's point term: mean ||F_dG(x) - x||_1 at points [M, 3] that must not move."""
    return (deform(points) - points).abs().sum(dim=-1).mean()


def vertex_match(
    deform: DeformationField,
    forward: DeformationField,
    template_points: torch.Tensor,
    prior_points: torch.Tensor,
) -> torch.Tensor:
    """The prior with its correspondences (ARAP keeps the proxy's vertex order): the forward field
    takes proxy vertex i to prior vertex i and F_dG takes it back, [N, 3] each -> scalar (a sum,
    as `chamfer`): sum ||F'_dG(v_i) - p_i||^2 + sum ||F_dG(p_i) - v_i||^2."""
    there = ((forward(template_points) - prior_points) ** 2).sum()
    back = ((deform(prior_points) - template_points) ** 2).sum()
    return there + back
