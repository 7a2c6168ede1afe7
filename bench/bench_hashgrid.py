"""Hash grid speed on this machine: points/s for forward, forward+backward, and +Adam step.

Variants side by side (same table, 16 levels x 2 features, + a 64-wide MLP head like the
template's): fused gather + index_add_ backward (default), gather via F.embedding (dense grad), plain indexing, sparse grads + SparseAdam,
dense levels via grid_sample, and optionally torch.compile (slow first call).

    .venv/bin/python bench/bench_hashgrid.py [--points 65536] [--log2-table 16] [--compile]
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")  # before torch: see sine_cli.py

import argparse
import time

import torch
from torch import nn

from render.hashgrid import HashGrid, HashGridConfig


def build(variant: str, cfg: HashGridConfig):
    kw = {
        "fused": {},
        "embedding": {"gather": "embedding"},
        "index": {"gather": "index"},
        "sparse": {"sparse": True},
        "grid_sample": {"dense_mode": "grid_sample"},
        "compile": {},
    }[variant]
    grid = HashGrid(cfg, **kw)
    mlp = nn.Sequential(nn.Linear(grid.output_dim, 64), nn.ReLU(), nn.Linear(64, 16))
    if variant == "sparse":
        opts = [torch.optim.SparseAdam([grid.table], lr=1e-2), torch.optim.Adam(mlp.parameters())]
    else:
        opts = [
            torch.optim.Adam(
                [{"params": [grid.table], "eps": 1e-15}, {"params": mlp.parameters()}], lr=1e-2
            )
        ]

    def f(x):
        return mlp(grid(x))

    if variant == "compile":
        f = torch.compile(f)
    return f, opts


def timeit(fn, repeats: int) -> float:
    """Best of `repeats` (the machine is shared: the minimum is the least disturbed run)."""
    fn()  # warm-up
    best = float("inf")
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--points", type=int, default=65536, help="points per batch")
    ap.add_argument("--log2-table", type=int, default=16, help="log2 rows per level")
    ap.add_argument(
        "--repeats", type=int, default=5, help="timed repeats per figure (best is kept)"
    )
    ap.add_argument("--compile", action="store_true", help="also time torch.compile")
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: leave default)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    cfg = HashGridConfig(log2_table=args.log2_table)
    variants = ["fused", "embedding", "index", "sparse", "grid_sample"] + (
        ["compile"] if args.compile else []
    )
    torch.manual_seed(0)
    x = torch.rand(args.points, 3) * 2 - 1
    print(
        f"hash grid 16x2, table 2^{args.log2_table}, {args.points} points, "
        f"{torch.get_num_threads()} threads"
    )
    print(f"{'variant':<12} {'fwd pts/s':>12} {'fwd+bwd pts/s':>14} {'+Adam pts/s':>12}")
    for variant in variants:
        f, opts = build(variant, cfg)

        def fwd(f=f):
            with torch.no_grad():
                f(x)

        def fwd_bwd(f=f, opts=opts):
            for o in opts:
                o.zero_grad(set_to_none=True)
            f(x).square().mean().backward()

        def step(f=f, opts=opts):
            fwd_bwd(f, opts)
            for o in opts:
                o.step()

        n = args.points
        t_f, t_fb, t_s = (timeit(fn, args.repeats) for fn in (fwd, fwd_bwd, step))
        print(f"{variant:<12} {n / t_f:>12,.0f} {n / t_fb:>14,.0f} {n / t_s:>12,.0f}")


if __name__ == "__main__":
    main()
