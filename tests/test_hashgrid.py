"""Hash grid: agrees with the slow reference, dense/hashed level split, exact gradients."""

import torch

from render.hashgrid import HashGrid, HashGridConfig, level_resolutions, reference_encode

SMALL = HashGridConfig(
    n_levels=6, n_features=2, log2_table=12, base_resolution=4, max_resolution=64, init_scale=1.0
)


def _grid(**kw) -> HashGrid:
    torch.manual_seed(0)
    return HashGrid(SMALL, **kw).double()


def test_resolutions_and_dense_levels():
    assert level_resolutions(SMALL) == [4, 6, 12, 21, 36, 63]
    g = _grid()
    # (R+1)^3 <= 4096 for R = 4, 6, 12 (2197) but not 21 (10648)
    assert g.level_dense == [True, True, True, False, False, False]
    assert g.level_sizes == [125, 343, 2197, 4096, 4096, 4096]
    assert g.table.shape == (125 + 343 + 2197 + 3 * 4096, 2)
    assert g.output_dim == 12


def test_matches_reference_all_variants():
    x = torch.rand(200, 3, dtype=torch.float64) * 2.2 - 1.1  # some points outside the box
    ref = reference_encode(_grid(), x)
    for kw in (
        {},
        {"gather": "embedding"},
        {"gather": "index"},
        {"sparse": True},
        {"dense_mode": "grid_sample"},
    ):
        out = _grid(**kw)(x)
        assert out.shape == (200, 12)
        torch.testing.assert_close(out, ref, rtol=0, atol=1e-12)


def test_interpolates_grid_values_at_vertices():
    # At a vertex of the coarsest level (R = 4) the feature is exactly that row of the table.
    g = _grid()
    x = torch.tensor([[-1.0, -1.0, -1.0], [-0.5, 0.0, 0.5]], dtype=torch.float64)
    out = g(x)[:, :2]
    # vertex (1, 2, 3) of a 5^3 grid -> row 1 + 2*5 + 3*25 = 86
    torch.testing.assert_close(out[0], g.table[0])
    torch.testing.assert_close(out[1], g.table[86])


def test_position_gradients_finite_differences():
    g = _grid()
    g.table.requires_grad_(False)
    x = (torch.rand(20, 3, dtype=torch.float64) * 1.8 - 0.9).requires_grad_(True)
    proj = torch.randn(12, dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda pts: g(pts) @ proj, (x,))


def test_table_gradients_match_reference_and_finite_differences():
    g = _grid()  # the fused gather/index_add path
    x = torch.rand(30, 3, dtype=torch.float64) * 2 - 1
    proj = torch.randn(12, dtype=torch.float64)
    (g(x) @ proj).sum().backward()
    grad = g.table.grad.clone()
    g.table.grad = None
    (reference_encode(g, x) @ proj).sum().backward()
    torch.testing.assert_close(grad, g.table.grad)
    # central differences on a few touched rows (the encoding is linear in the table)
    rows = torch.nonzero(grad.abs().sum(1))[:, 0][torch.randperm(10)[:5]]
    eps = 1e-6
    with torch.no_grad():
        for r in rows.tolist():
            for c in range(2):
                old = g.table[r, c].item()
                g.table[r, c] = old + eps
                up = (g(x) @ proj).sum().item()
                g.table[r, c] = old - eps
                down = (g(x) @ proj).sum().item()
                g.table[r, c] = old
                assert abs((up - down) / (2 * eps) - grad[r, c].item()) < 1e-6


def test_sparse_gradients_touch_only_used_rows():
    g = _grid(sparse=True)
    x = torch.rand(5, 3, dtype=torch.float64) * 2 - 1
    g(x).sum().backward()
    grad = g.table.grad
    assert grad.is_sparse
    dense = _grid(gather="embedding")
    dense(x).sum().backward()
    torch.testing.assert_close(grad.to_dense(), dense.table.grad)
    # at most 5 points * 6 levels * 8 corners rows are touched
    assert (dense.table.grad.abs().sum(1) > 0).sum() <= 5 * 6 * 8


def test_native_kernels_match_the_torch_reference():
    """The C++ kernels (CPU float32) give the torch path's features and table gradients
    bit for bit and its position gradients to float tolerance, on dense and hashed levels,
    with points outside the box and several features per level."""
    from render import native

    assert native.library() is not None, "the native kernels did not build (is g++ installed?)"
    for cfg in (SMALL, HashGridConfig(n_levels=4, n_features=4, log2_table=10, max_resolution=90)):
        torch.manual_seed(1)
        grid = HashGrid(cfg)
        torch.nn.init.normal_(grid.table)
        x = (torch.rand(3000, 3) * 2.2 - 1.1).requires_grad_(True)
        weights = torch.randn(3000, grid.output_dim)
        results = []
        for use_native in (False, True):
            grid.native = use_native
            assert grid._use_native(x) == use_native
            grid.table.grad, x.grad = None, None
            out = grid(x)
            (out * weights).sum().backward()
            results.append((out.detach(), grid.table.grad.clone(), x.grad.clone()))
        (ref, ref_table, ref_x), (out, out_table, out_x) = results
        torch.testing.assert_close(out, ref, rtol=0, atol=0)
        torch.testing.assert_close(out_table, ref_table, rtol=0, atol=0)
        torch.testing.assert_close(out_x, ref_x, rtol=1e-5, atol=1e-4)


def test_native_kernels_keep_nan_positions_in_the_table():
    """A NaN position gives NaN features (the loss check then stops the run), never a read
    outside the table."""
    grid = HashGrid(SMALL)
    x = torch.tensor([[float("nan"), 0.1, 0.2], [0.3, -0.4, 0.5]], requires_grad=True)
    out = grid(x)
    assert torch.isnan(out[0]).all() and torch.isfinite(out[1]).all()
    out.sum().backward()
    assert torch.isfinite(x.grad[1]).all() and torch.isnan(grid.table.grad).any()


def test_double_precision_uses_the_torch_path():
    assert not _grid()._use_native(torch.zeros(1, 3, dtype=torch.float64))
