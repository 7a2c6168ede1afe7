"""Multiresolution hash encoding (Instant-NGP) in plain, vectorised torch.

One parameter table holds every level's rows (per-level offsets, like tiny-cuda-nn). Levels whose
dense grid `(R+1)^3` fits in the table are indexed densely (no hashing, no collisions); finer
levels use the spatial hash `(x*1 ^ y*2654435761 ^ z*805459861) mod T`. All hashed levels are
computed in one batched pass (no Python loop over points); the interpolation is trilinear, so
gradients flow both to the table and to the input positions (needed when a deformation field
feeds the template).

Variants (for speed, measured in bench/bench_hashgrid.py):
- `gather="fused"`: the whole encoding as one custom autograd function -- the default. On the
  CPU (float32) it runs the native kernels of `render/csrc/hashgrid.cpp` (`render/native.py`;
  ~5x faster); elsewhere, or with `native=False`, the torch version (gather forward,
  `index_add_` backward, analytic position gradient), which is the tested reference;
- `gather="index"`: `table[idx]` (autograd backward = index_put/accumulate);
- `gather="embedding"`: `torch.nn.functional.embedding` (autograd's dense backward);
- `sparse=True`: embedding with sparse gradients, to be stepped with `torch.optim.SparseAdam`;
- `dense_mode="grid_sample"`: the dense levels through `F.grid_sample` on a view of the table.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from render import native

PRIMES = (1, 2654435761, 805459861)


class _HashEncode(torch.autograd.Function):
    """The whole encoding as one autograd node: x01 [N, 3], table [T, F] -> [N, L, F].

    Forward builds rows and trilinear weights without an autograd graph; backward scatters
    into the table with `index_add_` (~2x faster on CPU than `embedding_dense_backward`) and,
    only when the positions need a gradient, differentiates the trilinear weights analytically.
    """

    @staticmethod
    def forward(ctx, x01, table, grid):
        res = grid._res.to(x01.dtype)  # [L]
        pos = x01[:, None, :] * res[None, :, None]  # [N, L, 3]
        cell0 = torch.floor(pos).clamp_max_(res[None, :, None] - 1)
        frac = pos - cell0  # [N, L, 3]
        idx = grid._all_indices(cell0.long())  # [N, L, 8]
        wx, wy, wz = (torch.stack([1 - frac[..., k], frac[..., k]], dim=-1) for k in range(3))
        w = (wz[:, :, :, None, None] * wy[:, :, None, :, None] * wx[:, :, None, None, :]).view(
            idx.shape
        )  # [N, L, 8]
        n, n_lev, n_feat = idx.shape[0], idx.shape[1], table.shape[1]
        feats = table.index_select(0, idx.view(-1)).view(n * n_lev, 8, n_feat)
        out = torch.bmm(w.view(n * n_lev, 1, 8), feats).view(n, n_lev, n_feat)
        ctx.save_for_backward(table, idx, w, frac, res)
        return out

    @staticmethod
    def backward(ctx, grad_out):  # [N, L, F]
        table, idx, w, frac, res = ctx.saved_tensors
        n, n_lev, n_feat = grad_out.shape
        grad_x = grad_table = None
        if ctx.needs_input_grad[1]:
            values = (w[..., None] * grad_out[:, :, None, :]).view(-1, n_feat)  # [N*L*8, F]
            grad_table = torch.zeros_like(table).index_add_(0, idx.view(-1), values)
        if ctx.needs_input_grad[0]:
            feats = table.index_select(0, idx.view(-1)).view(n * n_lev, 8, n_feat)
            s = torch.bmm(feats, grad_out.reshape(n * n_lev, n_feat, 1))
            s = s.view(n, n_lev, 2, 2, 2)  # d out / d w, corners as [z, y, x]
            wx, wy, wz = (torch.stack([1 - frac[..., k], frac[..., k]], dim=-1) for k in range(3))
            sx = s[..., 1] - s[..., 0]  # [N, L, z, y]
            sy = s[:, :, :, 1, :] - s[:, :, :, 0, :]  # [N, L, z, x]
            sz = s[:, :, 1] - s[:, :, 0]  # [N, L, y, x]
            gx = (sx * wz[..., :, None] * wy[..., None, :]).sum((-1, -2))
            gy = (sy * wz[..., :, None] * wx[..., None, :]).sum((-1, -2))
            gz = (sz * wy[..., :, None] * wx[..., None, :]).sum((-1, -2))
            grad_x = (torch.stack([gx, gy, gz], dim=-1) * res[None, :, None]).sum(1)  # [N, 3]
        return grad_x, grad_table, None


class _NativeHashEncode(torch.autograd.Function):
    """`_HashEncode` through the C++ kernels (CPU, float32): x01 [N, 3], table [T, F] -> [N, L, F].

    Nothing but the inputs is saved: the backward recomputes rows and weights.
    """

    @staticmethod
    def forward(ctx, x01, table, grid):
        lib = native.library()
        x01, table = x01.contiguous(), table.contiguous()
        n, n_lev, n_feat = x01.shape[0], grid.cfg.n_levels, table.shape[1]
        out = torch.empty(n, n_lev, n_feat, dtype=table.dtype)
        lib.hash_encode_forward(
            native.pointer(x01), n, native.pointer(table), n_feat, n_lev, *grid._native_args(),
            native.pointer(out), torch.get_num_threads(),
        )  # fmt: skip
        ctx.save_for_backward(x01, table)
        ctx.grid = grid
        return out

    @staticmethod
    def backward(ctx, grad_out):  # [N, L, F]
        x01, table = ctx.saved_tensors
        grid, lib = ctx.grid, native.library()
        grad_out = grad_out.contiguous()
        n, n_lev, n_feat = grad_out.shape
        threads = torch.get_num_threads()
        grad_x = grad_table = None
        if ctx.needs_input_grad[1]:
            grad_table = torch.zeros_like(table)
            lib.hash_encode_backward_table(
                native.pointer(x01), n, n_feat, n_lev, *grid._native_args(),
                native.pointer(grad_out), native.pointer(grad_table), threads,
            )  # fmt: skip
        if ctx.needs_input_grad[0]:
            grad_x = torch.empty_like(x01)
            lib.hash_encode_backward_x(
                native.pointer(x01), n, native.pointer(table), n_feat, n_lev,
                *grid._native_args(), native.pointer(grad_out), native.pointer(grad_x), threads,
            )  # fmt: skip
        return grad_x, grad_table, None


@dataclass
class HashGridConfig:
    """Shape of a multiresolution hash grid."""

    n_levels: int = 16  # number of resolution levels
    n_features: int = 2  # features per level
    log2_table: int = 16  # log2 of the rows per (hashed) level
    base_resolution: int = 16  # cells per axis at the coarsest level
    max_resolution: int = 1024  # cells per axis at the finest level
    init_scale: float = 1e-4  # table initialised U(-s, s)


def level_resolutions(cfg: HashGridConfig) -> list[int]:
    """Cells per axis of each level: geometric from base to max resolution."""
    if cfg.n_levels == 1:
        return [cfg.base_resolution]
    growth = math.exp(
        (math.log(cfg.max_resolution) - math.log(cfg.base_resolution)) / (cfg.n_levels - 1)
    )
    return [int(math.floor(cfg.base_resolution * growth**level)) for level in range(cfg.n_levels)]


class HashGrid(nn.Module):
    """Encodes points of the box [lo, hi]^3 into `n_levels * n_features` features.

    forward(x [N, 3]) -> [N, n_levels * n_features]; points outside the box are clamped.
    """

    def __init__(
        self,
        cfg: HashGridConfig | None = None,
        bound: float = 1.0,
        gather: str = "fused",
        sparse: bool = False,
        dense_mode: str = "gather",
        native: bool = True,
    ):
        super().__init__()
        self.cfg = cfg = cfg or HashGridConfig()
        if gather not in ("fused", "embedding", "index"):
            raise ValueError(f"gather must be 'fused', 'embedding' or 'index', not {gather!r}")
        if dense_mode not in ("gather", "grid_sample"):
            raise ValueError(f"dense_mode must be 'gather' or 'grid_sample', not {dense_mode!r}")
        self.bound = float(bound)
        self.gather = gather
        self.sparse = sparse
        self.dense_mode = dense_mode
        self.native = native  # use the C++ kernels when they apply (see `_use_native`)
        table_size = 2**cfg.log2_table
        self.resolutions = level_resolutions(cfg)
        sizes, dense = [], []
        for res in self.resolutions:
            n_dense = (res + 1) ** 3
            dense.append(n_dense <= table_size)
            sizes.append(min(n_dense, table_size))
        offsets = [0]
        for s in sizes:
            offsets.append(offsets[-1] + s)
        self.level_sizes = sizes
        self.level_dense = dense
        self.level_offsets = offsets
        self.output_dim = cfg.n_levels * cfg.n_features
        self.table = nn.Parameter(
            (torch.rand(offsets[-1], cfg.n_features) * 2 - 1) * cfg.init_scale
        )  # [rows, F]
        # Per-level constants as buffers, [L]
        self.register_buffer("_res", torch.tensor(self.resolutions, dtype=torch.float32), False)
        self.register_buffer("_res_int", torch.tensor(self.resolutions, dtype=torch.int64), False)
        self.register_buffer("_offsets", torch.tensor(offsets[:-1], dtype=torch.int64), False)
        self.register_buffer("_sizes", torch.tensor(sizes, dtype=torch.int64), False)
        self.n_dense = sum(dense)  # dense levels are the first ones (resolution grows)
        self.register_buffer("_dense", torch.tensor(dense, dtype=torch.uint8), False)

    def _native_args(self) -> tuple[int, int, int, int]:
        """(res, offsets, dense pointers, log2_table) for the C++ kernels."""
        for buf in (self._res_int, self._offsets, self._dense):
            assert buf.device.type == "cpu" and buf.is_contiguous()
        return (
            self._res_int.data_ptr(),
            self._offsets.data_ptr(),
            self._dense.data_ptr(),
            self.cfg.log2_table,
        )

    def _use_native(self, x: torch.Tensor) -> bool:
        """The C++ kernels run for CPU float32 inputs when they are built (or can be)."""
        return (
            self.native
            and x.device.type == "cpu"
            and x.dtype == torch.float32
            and self.table.dtype == torch.float32
            and native.library() is not None
        )

    # ---- indexing -------------------------------------------------------------------------
    def _level_indices(self, cell0: torch.Tensor, levels: slice, dense: bool) -> torch.Tensor:
        """Lower cell corners [N, L', 3] (int64) -> table rows of the 8 corners [N, L', 8].

        Separable: per-axis pairs [N, L', 2] are combined by broadcasting (corner = x + 2y + 4z),
        so no [N, L', 8, 3] tensor is built.
        """
        n, n_lev = cell0.shape[:2]
        offsets = self._offsets[levels].view(1, -1, 1, 1, 1)  # [1, L', 1, 1, 1]
        if dense:  # x + y*(R+1) + z*(R+1)^2
            r1 = self._res_int[levels] + 1  # [L']
            strides = torch.stack([torch.ones_like(r1), r1, r1 * r1], dim=1)  # [L', 3]
            lo = cell0 * strides  # [N, L', 3]
            hi = lo + strides
            ax, ay, az = (torch.stack([lo[..., k], hi[..., k]], dim=-1) for k in range(3))
            idx = (
                az[:, :, :, None, None]
                + ay[:, :, None, :, None]
                + (ax[:, :, None, None, :] + offsets)
            )
        else:  # spatial hash
            parts = []
            for k in range(3):
                lo = cell0[..., k] * PRIMES[k]  # [N, L']
                parts.append(torch.stack([lo, lo + PRIMES[k]], dim=-1))  # [N, L', 2]
            ax, ay, az = parts
            idx = az[:, :, :, None, None] ^ ay[:, :, None, :, None] ^ ax[:, :, None, None, :]
            idx = (idx & (2**self.cfg.log2_table - 1)) + offsets
        return idx.view(n, n_lev, 8)

    def _all_indices(self, cell0: torch.Tensor) -> torch.Tensor:
        """Lower cell corners of every level [N, L, 3] -> rows [N, L, 8]."""
        parts = []
        if self.n_dense:
            parts.append(
                self._level_indices(cell0[:, : self.n_dense], slice(0, self.n_dense), True)
            )
        if self.n_dense < self.cfg.n_levels:
            hashed = slice(self.n_dense, self.cfg.n_levels)
            parts.append(self._level_indices(cell0[:, hashed], hashed, False))
        return torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]

    def _lookup(self, idx: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
        """Rows [N, L', 8] and weights [N, L', 8] -> interpolated features [N, L', F]."""
        if self.gather == "index" and not self.sparse:
            feats = self.table[idx]
        else:
            feats = F.embedding(idx, self.table, sparse=self.sparse)  # [N, L', 8, F]
        return (feats * w[..., None]).sum(dim=2)

    def _encode_levels(self, x01: torch.Tensor, levels: slice, dense: bool) -> torch.Tensor:
        """x in [0,1]^3 [N, 3] -> interpolated features [N, L', F] for the levels in `levels`."""
        res = self._res[levels].to(x01.dtype)  # [L']
        pos = x01[:, None, :] * res[None, :, None]  # [N, L', 3]
        cell0 = torch.floor(pos).clamp_max(res[None, :, None] - 1)  # [N, L', 3]
        frac = pos - cell0  # [N, L', 3], differentiable w.r.t. x
        idx = self._level_indices(cell0.long(), levels, dense)  # [N, L', 8]
        wx, wy, wz = (torch.stack([1 - frac[..., k], frac[..., k]], dim=-1) for k in range(3))
        w = wz[:, :, :, None, None] * wy[:, :, None, :, None] * wx[:, :, None, None, :]
        return self._lookup(idx, w.reshape(idx.shape))

    def _dense_grid_sample(self, x01: torch.Tensor) -> torch.Tensor:
        """Dense levels via F.grid_sample on views of the table -> [N, n_dense, F]."""
        grid = (x01 * 2 - 1).view(1, 1, 1, -1, 3).to(self.table.dtype)  # [1, 1, 1, N, 3]
        out = []
        for level in range(self.n_dense):
            r1 = self.resolutions[level] + 1
            o = self.level_offsets[level]
            vol = self.table[o : o + r1**3].view(r1, r1, r1, -1)  # [z, y, x, F]
            vol = vol.permute(3, 0, 1, 2)[None]  # [1, F, D, H, W]
            s = F.grid_sample(vol, grid, mode="bilinear", align_corners=True)  # [1, F, 1, 1, N]
            out.append(s.view(self.cfg.n_features, -1).t())
        return torch.stack(out, dim=1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """x [N, 3] world points in [-bound, bound]^3 -> features [N, L * F]."""
        x01 = ((x + self.bound) / (2 * self.bound)).clamp(0.0, 1.0)  # [N, 3]
        if self.gather == "fused" and not self.sparse and self.dense_mode == "gather":
            encode = _NativeHashEncode if self._use_native(x01) else _HashEncode
            feats = encode.apply(x01, self.table, self)  # [N, L, F]
            return feats.reshape(x.shape[0], self.output_dim)
        parts = []
        if self.n_dense:
            if self.dense_mode == "grid_sample":
                parts.append(self._dense_grid_sample(x01))
            else:
                parts.append(self._encode_levels(x01, slice(0, self.n_dense), True))
        if self.n_dense < self.cfg.n_levels:
            parts.append(self._encode_levels(x01, slice(self.n_dense, self.cfg.n_levels), False))
        feats = torch.cat(parts, dim=1) if len(parts) > 1 else parts[0]  # [N, L, F]
        return feats.reshape(x.shape[0], self.output_dim)


def reference_encode(grid: HashGrid, x: torch.Tensor) -> torch.Tensor:
    """Slow per-level, per-corner reference of `HashGrid.forward` (for tests)."""
    cfg = grid.cfg
    x01 = ((x + grid.bound) / (2 * grid.bound)).clamp(0.0, 1.0)
    out = []
    for level, res in enumerate(grid.resolutions):
        pos = x01 * res
        cell0 = torch.floor(pos).clamp_max(res - 1)
        frac = pos - cell0
        cell0 = cell0.long()
        acc = torch.zeros(x.shape[0], cfg.n_features, dtype=grid.table.dtype)
        for corner in range(8):
            bits = [(corner >> k) & 1 for k in range(3)]
            cx, cy, cz = (cell0[:, k] + bits[k] for k in range(3))
            if grid.level_dense[level]:
                idx = cx + cy * (res + 1) + cz * (res + 1) ** 2
            else:
                idx = (cx * PRIMES[0]) ^ (cy * PRIMES[1]) ^ (cz * PRIMES[2])
                idx = idx % grid.level_sizes[level]
            w = torch.ones(x.shape[0], dtype=x.dtype)
            for k in range(3):
                w = w * (frac[:, k] if bits[k] else 1 - frac[:, k])
            acc = acc + w[:, None] * grid.table[grid.level_offsets[level] + idx]
        out.append(acc)
    return torch.cat(out, dim=1)
