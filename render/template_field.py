"""The template radiance field (paper Sec. 3 / DESIGN.md section 7) and the background model.

TemplateField: hash grid (16 levels x 2 features) -> density head (1 hidden layer of 128) ->
sigma (trunc_exp) + a geometry feature; colour head (2 hidden layers of 64) on
[geometry feature, SH degree 4 of the view direction] -> rgb (sigmoid). The geometry feature
is exposed (`geo_feat`): a texture edit's F_dT reads it too (`--template-feature`).

Colour detail (`detail` set): a second hash grid, read only by the colour, whose features go
through a small MLP (with the direction encoding, not the geometry feature: with it the branch
fits the training views closer and the held-out ones less) into an offset of the colour head's
logits. Its last layer starts at zero, so a field with a fresh detail branch renders exactly as
without it. `sine fit` trains it last, on the frozen field (recon/colour_detail.py): density
never reads it, so the geometry the main fit found stays as it is.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import nn

from render.hashgrid import HashGrid, HashGridConfig
from render.sh import sh_encode


class _TruncExp(torch.autograd.Function):
    """exp(x) whose gradient uses exp(min(x, 15)) (Instant-NGP's density activation)."""

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.exp(x)

    @staticmethod
    def backward(ctx, g):
        (x,) = ctx.saved_tensors
        return g * torch.exp(x.clamp(max=15.0))


def trunc_exp(x: torch.Tensor) -> torch.Tensor:
    return _TruncExp.apply(x)


@dataclass
class TemplateFieldConfig:
    """Architecture of the template field."""

    grid: HashGridConfig = field(default_factory=lambda: HashGridConfig(log2_table=15))
    bound: float = 1.0  # the grid covers [-bound, bound]^3 (run units: object in the unit sphere)
    geo_feat_dim: int = 15  # geometry feature passed to the colour head (and to F_dT)
    density_hidden: int = 128  # hidden width of the density head (1 hidden layer)
    color_hidden: int = 64  # hidden width of the colour head (2 hidden layers)
    sh_degree: int = 4  # spherical-harmonics degree of the direction encoding
    density_activation: str = "trunc_exp"  # trunc_exp | softplus
    gather: str = "fused"  # hash-grid gather implementation (see render/hashgrid.py)
    detail: HashGridConfig | None = None  # the colour-detail grid (None: no detail branch)
    detail_hidden: int = 64  # hidden width of the colour-detail MLP (1 hidden layer)


def mlp(n_in: int, hidden: int, n_layers: int, n_out: int) -> nn.Sequential:
    layers: list[nn.Module] = []
    width = n_in
    for _ in range(n_layers):
        layers += [nn.Linear(width, hidden), nn.ReLU(inplace=True)]
        width = hidden
    layers.append(nn.Linear(width, n_out))
    return nn.Sequential(*layers)


class TemplateField(nn.Module):
    """x [N, 3] (run units), d [N, 3] unit directions -> sigma [N], rgb [N, 3], geo_feat [N, F]."""

    def __init__(self, cfg: TemplateFieldConfig | None = None):
        super().__init__()
        self.cfg = cfg = cfg or TemplateFieldConfig()
        self.grid = HashGrid(cfg.grid, bound=cfg.bound, gather=cfg.gather)
        self.density_net = mlp(self.grid.output_dim, cfg.density_hidden, 1, 1 + cfg.geo_feat_dim)
        self.color_net = mlp(cfg.geo_feat_dim + cfg.sh_degree**2, cfg.color_hidden, 2, 3)
        self.detail_grid = self.detail_net = None
        # whether queries add the detail offset: off while `sine fit`'s main steps train (the
        # branch is learnt after them, on the frozen field), on for every fitted field
        self.detail_active = True
        if cfg.detail is not None:
            self.detail_grid = HashGrid(cfg.detail, bound=cfg.bound, gather=cfg.gather)
            n_in = self.detail_grid.output_dim + cfg.sh_degree**2
            self.detail_net = mlp(n_in, cfg.detail_hidden, 1, 3)
            nn.init.zeros_(self.detail_net[-1].weight)  # starts as the field without detail
            nn.init.zeros_(self.detail_net[-1].bias)

    def _sigma_act(self, raw: torch.Tensor) -> torch.Tensor:
        if self.cfg.density_activation == "softplus":
            return nn.functional.softplus(raw - 1.0)
        return trunc_exp(raw)

    def geometry(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """x [N, 3] -> (sigma [N], geo_feat [N, F]); zero density outside the grid's box."""
        h = self.density_net(self.grid(x))  # [N, 1 + F]
        inside = (x.abs() <= self.cfg.bound).all(dim=-1)  # [N]
        sigma = self._sigma_act(h[:, 0]) * inside
        return sigma, h[:, 1:]

    def density(self, x: torch.Tensor) -> torch.Tensor:
        """Density only: x [N, 3] -> sigma [N]."""
        return self.geometry(x)[0]

    def color(
        self, geo_feat: torch.Tensor, d: torch.Tensor, x: torch.Tensor | None = None
    ) -> torch.Tensor:
        """geo_feat [N, F], d [N, 3], the points x [N, 3] (needed with a detail branch) -> rgb
        [N, 3] in (0, 1)."""
        return torch.sigmoid(self.color_logits(geo_feat, d, x, self.detail_active))

    def color_logits(self, geo_feat, d, x=None, detail: bool = True) -> torch.Tensor:
        """The colour before its sigmoid [N, 3] (arguments as `color`; `detail` False: without
        the detail branch's offset)."""
        sh = sh_encode(d, self.cfg.sh_degree)
        logits = self.color_net(torch.cat([geo_feat, sh], dim=-1))
        if detail and self.detail_grid is not None:
            if x is None:
                raise ValueError("a field with colour detail needs the points for its colour")
            logits = logits + self.detail_logits(x, sh)
        return logits

    def detail_logits(self, x: torch.Tensor, sh: torch.Tensor) -> torch.Tensor:
        """The detail branch's offset [N, 3] to the colour logits: x [N, 3], the direction's SH
        encoding [N, K]."""
        return self.detail_net(torch.cat([self.detail_grid(x), sh], dim=-1))

    def forward(self, x: torch.Tensor, d: torch.Tensor) -> dict[str, torch.Tensor]:
        """x [N, 3], d [N, 3] -> sigma, rgb, geo_feat."""
        sigma, geo = self.geometry(x)
        rgb = torch.sigmoid(self.color_logits(geo, d, x, detail=self.detail_active))
        return {"sigma": sigma, "rgb": rgb, "geo_feat": geo}

    def param_groups(self, lr_grid: float, lr_mlp: float, weight_decay_mlp: float = 1e-6):
        """Adam groups: the hash table (no weight decay, tiny eps) and the MLPs (without the
        detail branch: `detail_param_groups`)."""
        mlps = list(self.density_net.parameters()) + list(self.color_net.parameters())
        return [
            {"params": [self.grid.table], "lr": lr_grid, "eps": 1e-15, "name": "grid"},
            {"params": mlps, "lr": lr_mlp, "weight_decay": weight_decay_mlp, "name": "mlp"},
        ]

    def detail_param_groups(self, lr_grid: float, lr_mlp: float, weight_decay_mlp: float = 1e-6):
        """Adam groups of the detail branch: its hash table and its MLP ([] without one)."""
        if self.detail_grid is None:
            return []
        return [
            {
                "params": [self.detail_grid.table],
                "lr": lr_grid,
                "eps": 1e-15,
                "name": "detail_grid",
            },
            {
                "params": list(self.detail_net.parameters()),
                "lr": lr_mlp,
                "weight_decay": weight_decay_mlp,
                "name": "detail_mlp",
            },
        ]


class Background(nn.Module):
    """A constant background colour per dataset: fixed (e.g. from masks) or learned."""

    def __init__(self, color=(1.0, 1.0, 1.0), learnable: bool = False):
        super().__init__()
        color = torch.as_tensor(color, dtype=torch.float32)
        self.learnable = learnable
        if learnable:
            c = color.clamp(1e-3, 1 - 1e-3)
            self.logit = nn.Parameter(torch.log(c / (1 - c)))
        else:
            self.register_buffer("color", color.clone())

    def forward(self) -> torch.Tensor:  # [3]
        return torch.sigmoid(self.logit) if self.learnable else self.color


def freeze(module: nn.Module) -> nn.Module:
    """Freezes a field's parameters (eval mode, no parameter gradients) while gradients still
    flow through it to its inputs: a deformation in front of a frozen template learns through
    the template's positions. Never wrap such a template in `torch.no_grad` instead."""
    module.eval()
    for p in module.parameters():
        p.requires_grad_(False)
    return module
