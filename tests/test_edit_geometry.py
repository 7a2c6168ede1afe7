"""Geometric editing: losses on hand-made inputs, the deformation fields, gradients through a
frozen template, flow-to-3D lifting on a plane, the ARAP prior, symmetry, the edit's inputs, and
a tiny end-to-end edit (L_geo falls, exact resume, CLI errors, the edit's scene)."""

from __future__ import annotations

import json
import math
import shutil

import numpy as np
import open3d as o3d
import pytest
import torch
from feature_run_helpers import TINY_GEOMETRY_EDIT

import sine_cli
from edit import geometry_losses as L
from edit.deformation import DeformationField
from edit.edit_inputs import Target, difference_region, read_target
from edit.editing_field import EditingField, combine, edited_query
from edit.geometry_config import GeometryEditConfig
from edit.geometry_edit import run_geometry_edit
from edit.scene import load_scene
from edit.shape_prior import (
    Handles,
    arap_deform,
    back_project,
    lift_handles,
    lift_to_axes,
    lift_to_planes,
    lifting_normal,
    mirror_handles,
    mirror_plane,
    object_axes,
)
from edit.targets import stretch_axis, write_rgba
from recon.rundir import RunDir
from render.cameras import Camera, look_at
from render.errors import SineError
from render.hashgrid import HashGridConfig
from render.io import load_torch, write_mask
from render.raycast import MeshRaycaster
from render.renderer import render_rays
from render.sampler import UniformSampler
from render.template_field import TemplateField, TemplateFieldConfig, freeze


@pytest.fixture(autouse=True, scope="module")
def _one_thread():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the machine is shared: 1 thread avoids OpenMP stalls under load
    yield
    torch.set_num_threads(threads)


def _constant(field: DeformationField, offset) -> DeformationField:
    """Makes field(x) = x + offset exactly (output layer: zero weights, bias = offset)."""
    with torch.no_grad():
        field.mlp[-1].weight.zero_()
        field.mlp[-1].bias.copy_(torch.as_tensor(offset, dtype=torch.float32))
    return field


def _linear(field: DeformationField, a: torch.Tensor) -> DeformationField:
    """Makes field(x) = x + A x exactly: A x = relu(A x) - relu(-A x) on PE's copy of x."""
    with torch.no_grad():
        first, last = field.mlp[0], field.mlp[-1]
        first.weight.zero_()
        first.bias.zero_()
        first.weight[0:3, 0:3] = a
        first.weight[3:6, 0:3] = -a
        last.weight.zero_()
        last.bias.zero_()
        last.weight[:, 0:3] = torch.eye(3)
        last.weight[:, 3:6] = -torch.eye(3)
    return field


# ---- losses -------------------------------------------------------------------------------
def test_photometric_is_the_mean_squared_norm_over_rays():
    pred = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 0.0]])
    target = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 0.0]])
    assert L.photometric(pred, target).item() == pytest.approx((1.0 + 2.0) / 2)


def test_silhouette_bce_by_hand_and_clamped():
    opacity = torch.tensor([0.5, 0.9, 0.2])
    sil = torch.tensor([1.0, 1.0, 0.0])
    expected = -(math.log(0.5) + math.log(0.9) + math.log(0.8)) / 3
    assert L.silhouette_bce(opacity, sil).item() == pytest.approx(expected, rel=1e-5)
    # opacity 0 where the target has the object: finite, -log(1e-5)
    value = L.silhouette_bce(torch.tensor([0.0]), torch.tensor([1.0])).item()
    assert value == pytest.approx(-math.log(1e-5), rel=1e-4)


def test_chamfer_two_ways_sum_of_squared_nearest_distances():
    a = torch.tensor([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0]])
    b = torch.tensor([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0], [3.0, 0.0, 0.0]])
    # a -> b: 0 + 1; b -> a: 0 + 4 + 4
    assert L.chamfer(a, b).item() == pytest.approx(9.0, abs=1e-5)
    assert L.chamfer(b, a).item() == pytest.approx(9.0, abs=1e-5)
    assert L.chamfer(a, a).item() == pytest.approx(0.0, abs=1e-6)


def test_cycle_is_zero_for_inverse_fields_and_four_offsets_otherwise():
    a = torch.tensor([0.3, 0.0, 0.4])  # |a| = 0.5
    points = torch.rand(50, 3) * 2 - 1
    deform = _constant(DeformationField(), a)
    inverse = _constant(DeformationField(), -a)
    assert L.cycle(deform, inverse, points).item() == pytest.approx(0.0, abs=1e-6)
    same = _constant(DeformationField(), a)  # both ways off by 2a: 2 |2a| = 4 |a|
    assert L.cycle(deform, same, points).item() == pytest.approx(2.0, abs=1e-5)


def test_smoothness_is_zero_for_a_translation_and_the_jacobian_norm_for_a_linear_map():
    torch.manual_seed(0)
    points = torch.rand(64, 3) * 2 - 1
    eps = 0.01 * torch.randn(64, 3)
    shifted = _constant(DeformationField(), [0.2, -0.1, 0.05])
    # a translation is perfectly smooth: neither term penalises it (the identity part of
    # x + MLP(x) is not the deformation)
    assert L.deformation_smoothness(shifted, points, eps).item() == pytest.approx(0.0, abs=1e-5)
    a = torch.tensor([[0.1, 0.2, 0.0], [0.0, -0.3, 0.1], [0.2, 0.0, 0.05]])
    linear = _linear(DeformationField(), a)
    np.testing.assert_allclose(
        linear.jacobian_norm(points).detach().numpy(),
        np.full(64, torch.linalg.norm(a).item()),
        rtol=1e-5,
    )
    expected = torch.linalg.norm(a).item() + (eps @ a.T).abs().sum(dim=-1).mean().item()
    assert L.deformation_smoothness(linear, points, eps).item() == pytest.approx(expected, rel=1e-5)


def test_displacement_l1_is_the_mean_l1_offset():
    field = _constant(DeformationField(), [0.1, -0.2, 0.3])
    points = torch.rand(10, 3)
    assert L.displacement_l1(field, points).item() == pytest.approx(0.6, abs=1e-6)


# ---- deformation fields -------------------------------------------------------------------
def test_deformation_field_starts_near_identity_and_strength_zero_is_exact():
    torch.manual_seed(0)
    field = DeformationField()
    x = torch.rand(5000, 3) * 2 - 1
    with torch.no_grad():
        assert (field(x) - x).norm(dim=-1).max().item() < 1e-3
        _constant(field, [0.5, 0.5, 0.5])
        assert torch.equal(field(x, strength=0.0), x)
        np.testing.assert_allclose(field(x, strength=0.5) - x, 0.25, atol=1e-6)


def test_deformation_learns_through_a_frozen_template():
    torch.manual_seed(0)
    grid = HashGridConfig(n_levels=4, log2_table=10, base_resolution=4, max_resolution=32)
    template = TemplateField(TemplateFieldConfig(grid=grid))
    with torch.no_grad():
        template.grid.table.uniform_(-1.0, 1.0)  # a template with structure to learn through
    freeze(template)
    editing = EditingField(grid)
    query = edited_query(template, editing)
    n = 16
    origins = torch.tensor([[0.0, 0.0, 3.0]]).repeat(n, 1)
    dirs = torch.cat([0.1 * torch.randn(n, 2), -torch.ones(n, 1)], dim=1)
    dirs = dirs / dirs.norm(dim=-1, keepdim=True)
    out = render_rays(query, origins, dirs, UniformSampler(n_coarse=16, n_importance=0))
    assert out["hit"].all() and "mod" in out
    (combine(out).sum() + out["opacity"].sum()).backward()
    assert all(p.grad is None for p in template.parameters())  # frozen
    for name, p in editing.deform.named_parameters():
        assert p.grad is not None and p.grad.abs().sum() > 0, name
    assert all(p.grad is None for p in editing.forward_deform.parameters())  # not rendered
    assert editing.texture.mlp[-1].weight.grad.abs().sum() > 0  # F_dT through "mod"


# ---- flow-to-3D lifting on a plane --------------------------------------------------------
def _grid_plane(xs, ys, z):
    """A plane z = const as a triangulated grid: vertices [X*Y, 3], triangles."""
    gx, gy = np.meshgrid(xs, ys, indexing="ij")
    vertices = np.stack([gx.ravel(), gy.ravel(), np.full(gx.size, z)], axis=1)
    ny = len(ys)
    tris = []
    for i in range(len(xs) - 1):
        for j in range(ny - 1):
            a, b, c, d = i * ny + j, (i + 1) * ny + j, (i + 1) * ny + j + 1, i * ny + j + 1
            tris += [(a, b, c), (a, c, d)]
    return vertices, np.array(tris)


def test_lift_handles_back_projects_the_flow_at_the_vertex_depth():
    # camera on +z looking down at the plane z = 0: camera x = world x, camera y = -world y,
    # depth 3 everywhere; fx = fy = 64 on a 64x64 image
    cam = Camera(64, 64, 64.0, 64.0, 32.0, 32.0, look_at([0, 0, 3.0], [0, 0, 0], up=(0, 1, 0)))
    xs = np.linspace(-0.95, 0.95, 20)  # 0.05 + 0.1 k: no vertex projects onto a pixel border
    front, front_tris = _grid_plane(xs, xs, 0.0)
    back, back_tris = _grid_plane(0.5 * xs, 0.5 * xs, -0.5)  # hidden behind the front plane
    vertices = np.concatenate([front, back])
    triangles = np.concatenate([front_tris, back_tris + len(front)])
    depth = MeshRaycaster((vertices, triangles)).depth(cam)
    assert depth[32, 32] == pytest.approx(3.0, abs=1e-5)
    region = np.zeros((64, 64), bool)
    region[18:30, 32:46] = True  # world x in (0, 0.656), y in (0.094, 0.656)
    ones = np.ones((64, 64), np.float32)
    dx, dy = 2.5, -1.5
    flow = np.broadcast_to(np.array([dx, dy], np.float32), (64, 64, 2)).copy()
    handles = lift_handles(cam, vertices, depth, flow, region, ones, ones, visibility_tol=0.02)

    x, y = front[:, 0], front[:, 1]
    expected = np.nonzero((x > 0) & (x < 0.7) & (y > 0.1) & (y < 0.7))[0]
    assert len(expected) == 7 * 6
    np.testing.assert_array_equal(np.sort(handles.ids), expected)
    order = np.argsort(handles.ids)
    offset = np.array([dx * 3.0 / 64.0, -dy * 3.0 / 64.0, 0.0])  # camera y is world -y
    np.testing.assert_allclose(handles.targets[order], front[expected] + offset, atol=1e-6)
    # anchors: every vertex projecting outside the region, hidden ones too; hidden vertices
    # behind the region are free
    uv, _ = cam.project(vertices)
    in_region = region[uv[:, 1].astype(int), uv[:, 0].astype(int)]
    np.testing.assert_array_equal(handles.anchor_ids, np.nonzero(~in_region)[0])
    assert in_region[len(front) :].any()  # some hidden vertices are behind the region: free
    # sub-pixel motion is flow noise: no handles, the region's visible vertices anchored
    small = lift_handles(
        cam, vertices, depth, 0.4 * flow / np.hypot(dx, dy), region, ones, ones, 0.02
    )
    assert len(small.ids) == 0
    np.testing.assert_array_equal(small.anchor_ids, np.union1d(np.nonzero(~in_region)[0], expected))


def test_upright_lifting_turns_image_vertical_motion_into_vertical_motion():
    # a camera 30 degrees above the horizon looking at the origin; a point on the image's centre
    # column dragged 6 px up in the image: the upright plane (facing the camera, containing z)
    # lifts it straight up in the world, the image plane keeps its camera depth (tilted motion)
    eye = np.array([3.0 * math.cos(math.radians(30)), 0.0, 3.0 * math.sin(math.radians(30))])
    cam = Camera(64, 64, 64.0, 64.0, 32.0, 32.0, look_at(eye, [0, 0, 0]))
    point = np.array([[0.0, 0.0, 0.2]])
    uv, z = cam.project(point)
    assert uv[0, 0] == pytest.approx(32.0)  # on the centre column
    dst = uv + np.array([[0.0, -6.0]])
    up = np.array([0.0, 0.0, 1.0])
    upright = lift_to_planes(cam, dst, point, lifting_normal(cam, up))
    move = upright[0] - point[0]
    assert move[2] > 0 and np.abs(move[:2]).max() < 1e-9  # straight up
    image = lift_to_planes(cam, dst, point, lifting_normal(cam, None))
    np.testing.assert_allclose(cam.project(image)[1], z, atol=1e-9)  # same camera depth
    assert image[0, 0] < -0.01  # ... so it also moves away from the camera
    for lifted in (upright, image):
        np.testing.assert_allclose(cam.project(lifted)[0], dst, atol=1e-9)
    # a camera looking straight down has no upright plane: the image plane is used
    top = Camera(64, 64, 64.0, 64.0, 32.0, 32.0, look_at([0, 0, 3.0], [0, 0, 0], up=(0, 1, 0)))
    np.testing.assert_allclose(lifting_normal(top, up), lifting_normal(top, None))


def test_object_axes_of_a_long_box_and_of_a_square_one():
    corners = np.array([[x, y, z] for x in (-2, 2) for y in (-1, 1) for z in (0, 1)], float)
    up = np.array([0.0, 0.0, 1.0])
    axes = object_axes(corners, up)
    np.testing.assert_allclose(np.abs(axes), np.eye(3)[[2, 0, 1]], atol=1e-9)  # up, x, y
    square = corners * [0.5, 1.0, 1.0]  # as wide as long: no horizontal axis stands out
    np.testing.assert_allclose(object_axes(square, up), up[None])


def test_axis_lifting_moves_a_handle_along_the_axis_its_image_motion_follows():
    # a camera at 45 degrees azimuth, 20 degrees above the horizon: a point moved 0.3 along x
    # (a car made longer, seen from three quarters) is lifted back onto that move exactly, where
    # the upright plane (facing the camera) would move it across the view as well
    a, e = math.radians(45), math.radians(20)
    eye = 3.0 * np.array([math.cos(a) * math.cos(e), math.sin(a) * math.cos(e), math.sin(e)])
    cam = Camera(96, 96, 96.0, 96.0, 48.0, 48.0, look_at(eye, [0, 0, 0]))
    axes = np.eye(3)[[2, 0, 1]]
    points = np.array([[0.4, -0.2, 0.3], [0.4, -0.2, 0.3]])
    moves = np.array([[0.3, 0.0, 0.0], [0.2, 0.0, 0.2]])  # along x; along the xz diagonal
    dst = cam.project(points + moves)[0]
    lifted, explained = lift_to_axes(cam, dst, points, axes)
    np.testing.assert_allclose(lifted[0], points[0] + moves[0], atol=1e-9)
    assert explained.tolist() == [True, False]  # no single axis explains the diagonal drag
    upright = lift_to_planes(cam, dst[:1], points[:1], lifting_normal(cam, axes[0]))
    assert abs((upright - points[:1])[0, 1]) > 0.1  # the plane's guess moves it along y too


def test_back_project_inverts_project():
    cam = Camera(80, 60, 70.0, 75.0, 41.0, 29.0, look_at([1.0, -2.0, 1.5], [0, 0, 0]))
    points = np.random.default_rng(0).uniform(-0.5, 0.5, (20, 3))
    uv, z = cam.project(points)
    np.testing.assert_allclose(back_project(cam, uv, z), points, atol=1e-9)


# ---- ARAP prior and symmetry --------------------------------------------------------------
def test_arap_moves_handles_to_targets_keeps_anchors_and_bends_the_rest_smoothly():
    sphere = o3d.geometry.TriangleMesh.create_sphere(radius=1.0, resolution=12)
    v, tris = np.asarray(sphere.vertices), np.asarray(sphere.triangles)
    handles = np.nonzero(v[:, 2] > 0.8)[0]
    anchors = np.nonzero(v[:, 2] < -0.3)[0]
    lift = np.array([0.0, 0.0, 0.3])
    ids = np.concatenate([handles, anchors])
    out = arap_deform(v, tris, ids, np.concatenate([v[handles] + lift, v[anchors]]))
    np.testing.assert_allclose(out[handles], v[handles] + lift, atol=1e-6)
    np.testing.assert_allclose(out[anchors], v[anchors], atol=1e-6)
    free = np.setdiff1d(np.arange(len(v)), ids)
    dz = out[free, 2] - v[free, 2]
    assert (dz > 0).all() and (dz < 0.3).all()  # in between the anchors and the handles
    assert np.corrcoef(v[free, 2], dz)[0, 1] > 0.9  # higher vertices follow the handles more
    disp = out - v
    edges = np.concatenate([tris[:, [0, 1]], tris[:, [1, 2]], tris[:, [2, 0]]])
    jumps = np.linalg.norm(disp[edges[:, 0]] - disp[edges[:, 1]], axis=1)
    assert jumps.max() < 0.15  # neighbours move alike: no tearing


def test_mirror_plane_finds_the_symmetry_and_refuses_an_asymmetric_shape():
    rng = np.random.default_rng(0)
    half = rng.uniform([0.05, -0.3, -0.2], [0.6, 0.9, 0.2], (150, 3))  # not symmetric in y, z
    sym = np.concatenate([half, half * [-1, 1, 1]])
    plane = mirror_plane(sym)
    assert plane is not None
    np.testing.assert_allclose(np.abs(plane[:3]), [1.0, 0.0, 0.0], atol=1e-6)
    assert plane[3] == pytest.approx(0.0, abs=1e-6)
    assert mirror_plane(rng.uniform(-1, 1, (300, 3))) is None


def test_mirror_handles_mirrors_displacements_onto_free_opposite_vertices():
    v = np.array([[1, 0, 0], [-1, 0, 0], [1, 1, 0], [-1, 1, 0], [0, 2, 0]], float)
    delta = np.array([0.1, 0.2, 0.3])
    handles = Handles(np.array([0, 2, 4]), v[[0, 2, 4]] + delta, np.array([3]))
    out = mirror_handles(handles, v, np.array([1.0, 0.0, 0.0, 0.0]))
    # vertex 1 mirrors 0; 3 is an anchor and 4 lies on the plane: neither gets a new handle
    np.testing.assert_array_equal(out.ids, [0, 2, 4, 1])
    np.testing.assert_allclose(out.targets[3], v[1] + [-0.1, 0.2, 0.3])
    np.testing.assert_array_equal(out.anchor_ids, [3])


# ---- the edit's inputs --------------------------------------------------------------------
def _square_scene():
    rgb = np.full((64, 64, 3), 0.5, np.float32)
    alpha = np.zeros((64, 64), np.float32)
    alpha[16:48, 16:48] = 1.0
    rgb[alpha > 0] = [0.8, 0.3, 0.2]
    return rgb, alpha


def test_difference_region_says_nothing_to_edit_and_finds_a_changed_square():
    rgb, alpha = _square_scene()
    with pytest.raises(SineError, match="nothing to edit"):
        difference_region(Target(rgb, alpha, "alpha"), rgb, alpha, dilate_px=4)
    edited = rgb.copy()
    edited[20:30, 30:40] = [0.1, 0.6, 0.9]
    region = difference_region(Target(edited, alpha, "alpha"), rgb, alpha, dilate_px=4)
    assert region[20:30, 30:40].all()
    rows, cols = np.nonzero(region)
    # the square grown by the dilation (4 px) plus at most the blur's reach (2 px)
    assert 14 <= rows.min() <= 16 and 33 <= rows.max() <= 35
    assert 24 <= cols.min() <= 26 and 43 <= cols.max() <= 45


def test_read_target_alpha_aspect_and_resize(tmp_path, capsys):
    rgb, alpha = _square_scene()
    path = tmp_path / "t.png"
    write_rgba(path, rgb, alpha)
    target = read_target(path, (64, 64), background=[0.0, 0.0, 1.0])
    assert target.silhouette_source == "alpha"
    np.testing.assert_array_equal(target.silhouette, alpha)
    np.testing.assert_allclose(target.rgb[alpha == 0], [[0.0, 0.0, 1.0]] * int((alpha == 0).sum()))
    np.testing.assert_allclose(target.rgb[alpha == 1], [[0.8, 0.3, 0.2]] * 1024, atol=1 / 255)
    with pytest.raises(SineError, match="another aspect"):
        read_target(path, (64, 48))
    capsys.readouterr()
    big = read_target(path, (128, 128))
    notes = capsys.readouterr().out.splitlines()  # one plain line for the image and its alpha
    assert notes == [f"note: target {path} is 64x64; resized to the run's 128x128"]
    assert big.rgb.shape == (128, 128, 3) and big.silhouette.shape == (128, 128)
    assert big.silhouette[40:90, 40:90].all() and not big.silhouette[:25].any()
    with pytest.raises(SineError, match="does not exist"):
        read_target(tmp_path / "missing.png", (64, 64))


def test_read_target_refuses_an_empty_silhouette(tmp_path):
    rgb, alpha = _square_scene()
    path = tmp_path / "clear.png"
    write_rgba(path, rgb, np.zeros_like(alpha))  # fully transparent
    with pytest.raises(SineError, match="empty silhouette: it is fully transparent"):
        read_target(path, (64, 64))
    black = tmp_path / "black.png"
    write_mask(black, np.zeros_like(alpha))
    write_rgba(path, rgb, np.ones_like(alpha))  # opaque: the silhouette comes from --mask
    with pytest.raises(SineError, match="empty silhouette: its mask is black everywhere"):
        read_target(path, (64, 64), mask_path=black)


# ---- a tiny edit end to end ---------------------------------------------------------------
VIEW = 0


@pytest.fixture(scope="module")
def edit_run(tiny_fitted_run, tmp_path_factory):
    """A copy of the tiny fitted run with a target (view VIEW, the car's top stretched upward)
    and an uninterrupted 30-step edit "full"."""
    run = tmp_path_factory.mktemp("geo_edit") / "run"
    shutil.copytree(tiny_fitted_run, run)
    scene = load_scene(run, device="cpu")
    camera = RunDir(run).load_cameras().frames[VIEW]
    view = scene.render_view(camera)
    rows = np.nonzero((view["opacity"] > 0.5).any(axis=1))[0]
    middle = float(rows.min() + rows.max()) / 2
    top = np.zeros_like(view["opacity"])
    top[: int(middle)] = 1.0
    image, alpha = stretch_axis(view["rgb"], view["opacity"], "y", 1.3, middle, top)
    background = scene.background().detach().numpy()
    write_rgba(run / "target.png", image, alpha, background=background)
    cfg = GeometryEditConfig(**TINY_GEOMETRY_EDIT)
    metrics = run_geometry_edit(run, VIEW, run / "target.png", "full", cfg, progress=False)
    return run, metrics


def test_edit_lowers_l_geo_and_writes_its_outputs(edit_run):
    run, metrics = edit_run
    out = run / "edits" / "full"
    log = json.loads((out / "log.json").read_text())
    assert [e["step"] for e in log] == list(range(1, 31))
    losses = [e["loss"] for e in log]
    first, last = np.mean(losses[:5]), np.mean(losses[-5:])
    assert last < 0.8 * first, (first, last)
    for e in log:  # every term logged and summed into L_geo
        terms = ("photometric", "silhouette", "gp", "cyc", "gr", "reg")
        assert e["loss"] == pytest.approx(sum(e[k] for k in terms), rel=1e-5)
    assert metrics["iterations"] == 30 and metrics["prior_handles"] >= 1
    for name in ("edit_field.pt", "prior_mesh.ply", "region.png", "target.png", "metrics.json"):
        assert (out / name).is_file(), name
    assert not (run / "edits" / "full.partial").exists()


def test_interrupted_edit_resumes_bit_exactly(edit_run):
    run, _ = edit_run
    cfg = GeometryEditConfig(**TINY_GEOMETRY_EDIT)
    # stop between two sampler rebuilds (every 25 steps): the resumed run must sample as before
    assert run_geometry_edit(
        run, VIEW, run / "target.png", "resumed", cfg, progress=False, stop_at=12
    ) == {"step": 12}
    assert (run / "edits" / "resumed.partial" / "checkpoint.pt").is_file()
    assert not (run / "edits" / "resumed").exists()
    metrics = run_geometry_edit(run, VIEW, run / "target.png", "resumed", cfg, progress=False)
    assert metrics["iterations"] == 30
    full = load_torch(run / "edits" / "full" / "edit_field.pt")["editing"]
    resumed = load_torch(run / "edits" / "resumed" / "edit_field.pt")["editing"]
    assert full.keys() == resumed.keys()
    for k in full:
        assert torch.equal(full[k], resumed[k]), k
    # finished with the same options: skipped
    again = run_geometry_edit(run, VIEW, run / "target.png", "resumed", cfg, progress=False)
    assert again["skipped"]


def test_edit_cli_errors_are_one_line_with_exit_code_2(edit_run, capsys):
    run, _ = edit_run
    target = str(run / "target.png")
    capsys.readouterr()
    assert sine_cli.main(["edit", str(run), "--target", target, "--view", "99", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: --view 99 is out of range") and "\n" not in err
    missing = str(run / "missing.png")
    assert sine_cli.main(["edit", str(run), "--target", missing, "--view", "0", "--quiet"]) == 2
    err = capsys.readouterr().err.strip()
    assert "missing.png does not exist" in err and "\n" not in err
    snap = str(run / "snapshot.png")
    assert sine_cli.main(["snapshot", str(run), "--view", str(VIEW), "--out", snap]) == 0
    capsys.readouterr()
    args = ["edit", str(run), "--target", snap, "--view", str(VIEW), "--name", "same", "--quiet"]
    assert sine_cli.main(args) == 2
    err = capsys.readouterr().err.strip()
    assert "nothing to edit" in err and "\n" not in err
    assert not (run / "edits" / "same").exists()


def test_edit_scene_renders_and_colours_its_mesh(edit_run):
    run, _ = edit_run
    camera = RunDir(run).load_cameras().frames[VIEW]
    scene = load_scene(run, edit="full", device="cpu")
    assert scene.name == "full"
    view = scene.render_view(camera)
    assert view["rgb"].shape == (64, 64, 3) and np.isfinite(view["rgb"]).all()
    assert (view["opacity"] > 0.5).sum() > 100
    assert view["rgb"].min() >= 0 and view["rgb"].max() <= 1
    vertices, triangles, colours = scene.colored_mesh()
    proxy, _ = load_scene(run, device="cpu").mesh()
    assert vertices.shape == proxy.shape and not np.allclose(vertices, proxy)  # F'_dG warped
    assert colours.shape == (len(vertices), 3)
    assert colours.min() >= 0.0 and colours.max() <= 1.0
    with pytest.raises(SineError, match="not found"):
        load_scene(run, edit="nope", device="cpu")


def test_edit_gate_values_and_reload():
    """1 within `inner` of the points, 0 beyond `outer`, linear between; 1 everywhere unset;
    a saved gate reloads at its own resolution; the fields' outputs are scaled by it."""
    from edit.edit_gate import EditGate
    from edit.editing_field import EditingField

    x = torch.tensor([[0.5, 0.0, 0.0], [0.75, 0.0, 0.0], [0.95, 0.0, 0.0], [-0.5, 0.0, 0.0]])
    assert torch.equal(EditGate()(x), torch.ones(4))
    editing = EditingField()
    editing.gate.set_from_points(np.array([[0.5, 0.0, 0.0]]), inner=0.1, outer=0.4, resolution=64)
    w = editing.gate(x)
    assert w[0] == pytest.approx(1.0)
    assert w[1] == pytest.approx(0.5, abs=0.08)  # distance 0.25: halfway (voxel 1/32)
    assert w[2] == 0.0 and w[3] == 0.0
    with torch.no_grad():
        editing.deform.mlp[-1].bias.fill_(0.1)
    disp = editing.deform(x) - x
    assert torch.allclose(disp[:, 0], 0.1 * w, atol=1e-3)
    reloaded = EditingField()
    reloaded.load_state_dict(editing.state_dict())
    assert reloaded.gate.grid.shape == (1, 1, 64, 64, 64)
    assert torch.equal(reloaded.gate(x), w) and reloaded.texture.gate is reloaded.gate


def test_edit_gate_vote_outvotes_stray_points_and_stops_at_the_neighbours_surface():
    """A part's surface along x in [0, 0.28], its neighbour's along [0.32, 0.6], and two stray
    part points at x = 0.5 (one view's mask wrongly reaching over the neighbour): without the
    others' votes the gate opens around the strays; with them it is 0 there and stays 1 on the
    part and just off its surface."""
    from edit.edit_gate import EditGate

    line = np.zeros((50, 3))
    part, neighbour = line.copy(), line.copy()
    part[:, 0], neighbour[:, 0] = np.linspace(0.0, 0.28, 50), np.linspace(0.32, 0.6, 50)
    stray = np.array([[0.5, 0.0, 0.0], [0.505, 0.0, 0.0]])
    x = torch.tensor([[0.1, 0.0, 0.0], [0.1, 0.04, 0.0], [0.47, 0.0, 0.0], [0.5, 0.0, 0.0]])
    union, vote = EditGate(), EditGate()
    union.set_from_points(np.concatenate([part, stray]), inner=0.05, outer=0.1, resolution=64)
    assert (union(x) > 0.5).all()
    vote.set_from_points(np.concatenate([part, stray]), 0.05, 0.1, 64, others=neighbour)
    w = vote(x)
    assert w[0] == 1.0 and w[1] == 1.0
    assert w[2] == 0.0 and w[3] == 0.0


def test_edit_gate_vote_keeps_a_hole_the_part_encloses():
    """A flat patch of the part (z = 0, x and y in [0, 0.3]) whose points in one voxel are all
    called something else by the views (a spot their masks miss): the vote alone gives that
    voxel away and the stop zeroes the gate there; the part's voxels enclose it, so it stays
    the part's. The neighbour's patch beside it (x in [0.36, 0.6]) stays shut."""
    from edit.edit_gate import EditGate

    grid = np.linspace(0.0, 0.3, 41)
    xs, ys = np.meshgrid(grid, grid)
    part = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    voxel = 2.0 / 64  # the hole: the voxel holding (0.15, 0.15, 0), [0.125, 0.15625) in x and y
    in_hole = np.all((part[:, :2] >= 0.125) & (part[:, :2] < 0.125 + voxel), axis=1)
    hole = part[in_hole]
    neighbour = part[~in_hole][:200].copy()
    neighbour[:, 0] = 0.36 + 0.8 * neighbour[:, 0]
    gate = EditGate()
    gate.set_from_points(part[~in_hole], 0.02, 0.05, 64, others=np.concatenate([hole, neighbour]))
    centres = [[0.140625, 0.140625], [0.046875, 0.234375], [0.453125, 0.109375]]  # voxels'
    x = torch.tensor([[a, b, voxel / 2] for a, b in centres])
    assert gate(x).tolist() == [1.0, 1.0, 0.0]


def test_edit_gate_closes_the_same_hole_on_a_finer_grid():
    """The hole above (1/32 of a unit square, one voxel at 64) is 4 x 4 voxels at 256: the
    closing keeps its reach in run units (2 voxels at 256), so the part keeps it there too;
    the neighbour's patch 0.06 away stays shut."""
    from edit.edit_gate import EditGate

    grid = np.linspace(0.0, 0.3, 121)
    xs, ys = np.meshgrid(grid, grid)
    part = np.stack([xs.ravel(), ys.ravel(), np.zeros(xs.size)], axis=1)
    in_hole = np.all((part[:, :2] >= 0.125) & (part[:, :2] < 0.125 + 2.0 / 64), axis=1)
    neighbour = part[~in_hole][:2000].copy()
    neighbour[:, 0] = 0.36 + 0.8 * neighbour[:, 0]
    gate = EditGate()
    others = np.concatenate([part[in_hole], neighbour])
    gate.set_from_points(part[~in_hole], 0.02, 0.05, 256, others=others)
    voxel = 2.0 / 256
    x = torch.tensor([[0.140625, 0.140625, voxel / 2], [0.45, 0.1, voxel / 2]])
    assert gate(x).tolist() == [1.0, 0.0]


def test_an_identity_edit_renders_the_template_exactly_in_the_fit_band(tiny_fitted_run):
    """Sampled in the template fit's band (the default: band_width None), an editing field
    that moves nothing renders the template's pixels; a wider band samples other points, so
    even untouched parts of an edit would differ from the template."""
    from edit.editing_scene import deformed_template
    from edit.geometry_config import with_fit_band
    from edit.template_scene import load_template_scene

    scene = load_template_scene(RunDir(tiny_fitted_run), torch.device("cpu"))
    freeze(scene.field)
    band = with_fit_band(GeometryEditConfig(), scene.fit_config).band_width
    assert band == scene.fit_config.band_width
    identity = EditingField(scene.field.grid.cfg)
    for deform in (identity.deform, identity.forward_deform):
        torch.nn.init.zeros_(deform.mlp[-1].weight)
        torch.nn.init.zeros_(deform.mlp[-1].bias)
    cam = RunDir(tiny_fitted_run).load_cameras().frames[3]
    reference = scene.render_view(cam)["rgb"]
    same = deformed_template(scene, freeze(identity), band).render_view(cam)["rgb"]
    wider = deformed_template(scene, freeze(identity), band + 0.01).render_view(cam)["rgb"]
    assert np.abs(same - reference).max() < 1e-4
    assert np.abs(wider - reference).max() > 1e-3
