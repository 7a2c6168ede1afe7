"""Synthetic turntables: the ground truth must agree with itself (depth on the mesh, masks, labels,
cameras) and the GT edits must do exactly what they say."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from recon.synth import SynthConfig, load_source, sample_texture, synthesize
from recon.synth_edits import stretch_displacement
from recon.synth_mesh import load_mesh_file, normalise
from recon.synth_render import render_views, ring_cameras
from render.cameras import cameras_from_transforms, load_cameras
from render.errors import SineError
from render.io import read_depth, read_image, read_label_map, read_mask

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
SPOT = DATA / "meshes" / "spot" / "spot_triangulated.obj"
# One ray per pixel: the tests below compare pixels with the labels/depth of the same ray
# (supersampling blends colours across part edges; tested on its own).
SMALL = dict(views=8, width=96, height=72, supersample=1)


@pytest.fixture(scope="module")
def toycar(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("toycar")
    cfg = SynthConfig(out=out, procedural="toycar", edit=["geometric", "texture"], **SMALL)
    synthesize(cfg, progress=False)
    return out


@pytest.fixture(scope="module")
def spot(tmp_path_factory) -> Path:
    if not SPOT.is_file():
        pytest.skip("../shared/data/meshes/spot is missing")
    out = tmp_path_factory.mktemp("spot")
    synthesize(SynthConfig(out=out, mesh=SPOT, edit=["geometric"], **SMALL), progress=False)
    return out


def _load_mesh(path: Path):
    import trimesh

    return trimesh.load(str(path), process=False)


def _unproject(cam, depth: np.ndarray) -> np.ndarray:
    """World points [N, 3] of the pixels with depth > 0."""
    rows, cols = np.nonzero(depth > 0)
    z = depth[rows, cols].astype(np.float64)
    x = (cols + 0.5 - cam.cx) / cam.fx * z
    y = (rows + 0.5 - cam.cy) / cam.fy * z
    c2w = cam.camera_to_world
    return np.stack([x, y, z], 1) @ c2w[:3, :3].T + c2w[:3, 3]


def _surface_distance(mesh, points: np.ndarray) -> np.ndarray:
    import open3d as o3d

    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(
        o3d.core.Tensor(np.asarray(mesh.vertices, np.float32)),
        o3d.core.Tensor(np.asarray(mesh.faces, np.uint32)),
    )
    return scene.compute_distance(o3d.core.Tensor(points.astype(np.float32))).numpy()


def _check_depth_on_surface(run: Path) -> float:
    mesh = _load_mesh(run / "mesh.ply")
    diagonal = float(np.linalg.norm(mesh.bounds[1] - mesh.bounds[0]))
    worst = 0.0
    for cam in load_cameras(run / "cameras.json").frames:
        depth = read_depth(run / "depth" / (Path(cam.name).stem + ".npy"))
        assert (depth > 0).sum() > 100  # the object is in view
        dist = _surface_distance(mesh, _unproject(cam, depth))
        worst = max(worst, float(dist.max()) / diagonal)
    assert worst < 1e-3
    return worst


# ---- ground truth agrees with itself -------------------------------------------------------
def test_depth_reprojects_to_mesh_surface_procedural(toycar):
    _check_depth_on_surface(toycar)
    _check_depth_on_surface(toycar / "edits" / "geometric")


def test_depth_reprojects_to_mesh_surface_spot(spot):
    _check_depth_on_surface(spot)
    _check_depth_on_surface(spot / "edits" / "geometric")


@pytest.mark.parametrize("which", ["toycar", "spot"])
def test_masks_labels_depth_consistent(which, request):
    run = request.getfixturevalue(which)
    parts = {int(k) for k in json.loads((run / "parts.json").read_text())}
    seen = set()
    for cam in load_cameras(run / "cameras.json").frames:
        stem = Path(cam.name).stem
        mask = read_mask(run / "masks" / f"{stem}.png")
        depth = read_depth(run / "depth" / f"{stem}.npy")
        labels = read_label_map(run / "labels" / f"{stem}.png")
        image = read_image(run / "images" / f"{stem}.png")
        assert mask.shape == depth.shape == labels.shape == image.shape[:2] == (72, 96)
        np.testing.assert_array_equal(mask, depth > 0)
        np.testing.assert_array_equal(mask, labels > 0)
        # white background; a pixel the object only partly covers blends (supersampling)
        near = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        assert np.all(image[~near] == 1.0)
        seen |= set(np.unique(labels[mask]).tolist())
    assert seen <= parts
    assert len(seen) >= 2  # several parts are visible


def test_supersampling_averages_the_rays_over_each_pixel():
    """supersample 3: each pixel's colour is the mean of the 3 x 3 rays a 3x larger camera casts
    over it; mask, depth and labels are the centre ray's, i.e. what one ray per pixel gives."""
    mesh, _, _ = load_source(SynthConfig(procedural="toycar"))
    cam = ring_cameras(1, 24, 16, [20.0], 3.0, 40.0)[0]
    single = render_views(mesh, [cam])[0]
    fine = render_views(mesh, [cam.resized(72, 48)])[0]
    ss = render_views(mesh, [cam], supersample=3)[0]
    expected = fine["rgb"].reshape(16, 3, 24, 3, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(ss["rgb"], expected, atol=1e-6)
    for key in ("mask", "depth", "labels"):
        np.testing.assert_array_equal(ss[key], single[key])
    edge = ss["mask"] != (cv2.dilate(ss["mask"].astype(np.uint8), np.ones((3, 3))) > 0)
    assert np.abs(ss["rgb"] - single["rgb"])[edge].max() > 0.05  # the silhouette is softened
    with pytest.raises(SineError, match="odd"):
        render_views(mesh, [cam], supersample=2)


def test_plane_parts_follow_the_plane(spot):
    """A single-material mesh is split by the horizontal plane z = 0: label 2 above, 1 below."""
    assert json.loads((spot / "parts.json").read_text()) == {"1": "below", "2": "above"}
    for cam in load_cameras(spot / "cameras.json").frames[:3]:
        stem = Path(cam.name).stem
        depth = read_depth(spot / "depth" / f"{stem}.npy")
        labels = read_label_map(spot / "labels" / f"{stem}.png")
        z = _unproject(cam, depth)[:, 2]
        lab = labels[depth > 0]
        assert np.all(z[lab == 2] > -1e-4) and np.all(z[lab == 1] < 1e-4)


def test_vertices_project_inside_masks(toycar):
    mesh = _load_mesh(toycar / "mesh.ply")
    for cam in load_cameras(toycar / "cameras.json").frames:
        mask = read_mask(toycar / "masks" / (Path(cam.name).stem + ".png"))
        grown = cv2.dilate(mask.astype(np.uint8), np.ones((3, 3), np.uint8)) > 0
        uv, z = cam.project(mesh.vertices)
        assert np.all(z > 0)
        col, row = np.floor(uv[:, 0]).astype(int), np.floor(uv[:, 1]).astype(int)
        inside = (col >= 0) & (col < cam.width) & (row >= 0) & (row < cam.height)
        assert inside.all()  # the whole object is in the frame
        assert grown[row, col].all()


def test_normalised_mesh_is_centred_and_fits(toycar, spot):
    for run in (toycar, spot):
        mesh = _load_mesh(run / "mesh.ply")
        np.testing.assert_allclose(mesh.bounds.mean(axis=0), 0.0, atol=1e-5)
        assert abs(np.linalg.norm(mesh.vertices, axis=1).max() - 0.8) < 1e-5
        synth = json.loads((run / "synth.json").read_text())
        assert synth["normalization"]["scale"] > 0
    assert json.loads((spot / "synth.json").read_text())["up_axis"] == "y"


def test_transforms_parse_back_to_the_same_cameras(toycar):
    transforms = json.loads((toycar / "transforms.json").read_text())
    cams = load_cameras(toycar / "cameras.json").frames
    parsed = cameras_from_transforms(transforms)
    assert len(parsed) == len(cams) == 8
    for (path, cam), ref, frame in zip(parsed, cams, transforms["frames"], strict=True):
        assert path == f"images/{ref.name}"
        np.testing.assert_allclose(cam.K, ref.K, atol=1e-9)
        np.testing.assert_allclose(cam.camera_to_world, ref.camera_to_world, atol=1e-9)
        for key in ("file_path", "mask_path", "depth_file_path", "label_path"):
            assert (toycar / frame[key]).is_file()
        assert frame["split"] == ref.split
    assert [c.split for c in cams] == ["train"] * 7 + ["test"]  # the same rule as ingest


# ---- cameras ----------------------------------------------------------------------------
def test_ring_cameras_look_at_origin_upright():
    cams = ring_cameras(6, 64, 48, elevations_deg=[10.0, 45.0], radius=3.0, fov_deg=40.0)
    assert [c.name for c in cams] == [f"r_{i:03d}.png" for i in range(6)]
    expected_f = 24.0 / np.tan(np.radians(20.0))  # 40 degrees across the 48-pixel side
    for i, cam in enumerate(cams):
        assert cam.fx == pytest.approx(expected_f) and cam.cx == 32.0 and cam.cy == 24.0
        assert np.linalg.norm(cam.center) == pytest.approx(3.0)
        elevation = np.degrees(np.arcsin(cam.center[2] / 3.0))
        assert elevation == pytest.approx(10.0 if i < 3 else 45.0)
        uv, z = cam.project(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 0.3]]))
        np.testing.assert_allclose(uv[0], [32.0, 24.0], atol=1e-9)  # origin at the centre
        assert uv[1, 1] < 24.0  # +z is up in the image
    azimuths = [np.degrees(np.arctan2(c.center[1], c.center[0])) % 360 for c in cams[:3]]
    np.testing.assert_allclose(azimuths, [0.0, 120.0, 240.0], atol=1e-9)


# ---- edits ------------------------------------------------------------------------------
def test_stretch_displacement_hand_computed():
    pts = np.array([[0.3, 0.1, -0.1], [0.0, 0.0, 0.05], [0.2, -0.4, 0.5]])
    d = stretch_displacement(pts, [0, 0, 2.0, 0.0], scale=1.5, falloff=0.1)  # plane z = 0
    np.testing.assert_allclose(d[:, :2], 0.0)
    # z = 0.05: u = 0.5, G = 0.1 * (0.125 - 0.03125) = 0.009375; * (1.5 - 1)
    # z = 0.5: beyond the band, G = 0.5 - 0.05 = 0.45
    np.testing.assert_allclose(d[:, 2], [0.0, 0.0046875, 0.225])


def test_geometric_edit_moves_only_vertices_above_plane(toycar):
    edit = json.loads((toycar / "edits" / "geometric" / "edit.json").read_text())
    before = np.asarray(_load_mesh(toycar / "mesh.ply").vertices)
    after = np.asarray(_load_mesh(toycar / "edits" / "geometric" / "mesh.ply").vertices)
    assert len(after) > len(before)  # the stretched faces split: their vertices appended
    after = after[: len(before)]
    normal, offset = np.asarray(edit["plane"][:3]), edit["plane"][3]
    s = before @ normal - offset
    np.testing.assert_array_equal(after[s <= 0], before[s <= 0])
    far = s >= edit["falloff"]
    assert far.sum() >= 4  # the cabin's roof corners at least
    expected = (edit["scale"] - 1.0) * (s[far] - 0.5 * edit["falloff"])
    np.testing.assert_allclose((after - before)[far] @ normal, expected, atol=1e-5)
    np.testing.assert_allclose(np.cross(after[far] - before[far], normal), 0.0, atol=1e-5)
    assert edit["vertices_moved"] == int((s > 0).sum())


def test_texture_edit_changes_only_the_part(toycar):
    edit = json.loads((toycar / "edits" / "texture" / "edit.json").read_text())
    assert edit["operation"] == "recolor_part" and edit["part_name"] == "body"
    changed_total = 0
    for cam in load_cameras(toycar / "cameras.json").frames:
        stem = Path(cam.name).stem
        labels = read_label_map(toycar / "labels" / f"{stem}.png")
        edited_labels = read_label_map(toycar / "edits" / "texture" / "labels" / f"{stem}.png")
        np.testing.assert_array_equal(labels, edited_labels)
        before = cv2.imread(str(toycar / "images" / f"{stem}.png"))
        after = cv2.imread(str(toycar / "edits" / "texture" / "images" / f"{stem}.png"))
        changed = np.any(before != after, axis=2)
        assert not changed[labels != edit["part"]].any()
        changed_total += changed.sum()
        assert changed[labels == edit["part"]].mean() > 0.5
    assert changed_total > 0


# ---- pieces -----------------------------------------------------------------------------
def test_sample_texture_bilinear():
    tex = np.zeros((2, 2, 3), np.float32)
    tex[0, 0], tex[0, 1], tex[1, 0], tex[1, 1] = 0.0, 1.0, 0.5, 0.25  # row 0 is v = 1 (top)
    uv = np.array([[0.5, 0.5], [0.25, 0.75], [0.75, 0.25], [0.5, 0.75]])
    out = sample_texture(tex, uv)[:, 0]
    np.testing.assert_allclose(out, [0.4375, 0.0, 0.25, 0.5], atol=1e-6)


def test_normalise_up_axis_y_to_z(tmp_path):
    obj = tmp_path / "tall.obj"
    obj.write_text("v 0 0 0\nv 1 0 0\nv 0 4 0\nf 1 2 3\n")
    mesh, norm = normalise(load_mesh_file(obj), "y")
    extent = mesh.vertices.max(axis=0) - mesh.vertices.min(axis=0)
    assert extent[2] == pytest.approx(4 * extent[0])  # the source y axis is now z
    np.testing.assert_allclose(norm.apply(norm.invert(mesh.vertices)), mesh.vertices, atol=1e-12)


# ---- errors -----------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(mesh=Path("/nonexistent/mesh.obj")), "does not exist"),
        (dict(procedural="toycar", views=2), "at least 3"),
        (dict(), "exactly one"),
        (dict(procedural="toycar", mesh=Path("x.obj")), "exactly one"),
        (dict(procedural="spaceship"), "unknown procedural"),
        (dict(procedural="toycar", edit=["texture"], edit_part=9), "not a part"),
        (dict(procedural="toycar", edit=["texture"], edit_texture=SPOT), "UV texture"),
    ],
)
def test_user_errors(tmp_path, kwargs, message):
    if kwargs.get("edit_texture") is not None and not SPOT.is_file():
        pytest.skip("needs the spot texture image")
    if "edit_texture" in kwargs:
        kwargs["edit_texture"] = SPOT.parent / "spot_texture.png"
    with pytest.raises(SineError, match=message):
        synthesize(SynthConfig(out=tmp_path / "out", width=32, height=24, **kwargs), progress=False)


def test_unreadable_mesh(tmp_path):
    bad = tmp_path / "bad.glb"
    bad.write_bytes(b"this is not a mesh")
    with pytest.raises(SineError):
        synthesize(SynthConfig(out=tmp_path / "out", mesh=bad), progress=False)
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing\n")
    with pytest.raises(SineError, match="no triangles"):
        synthesize(SynthConfig(out=tmp_path / "out", mesh=empty), progress=False)


def test_cli_help_and_exit_code(tmp_path, capsys):
    import sine_cli

    parser = sine_cli.build_parser(["synth"])
    sub = next(a for a in parser._actions if a.dest == "command").choices["synth"]
    for action in sub._actions:
        assert action.help, action.dest
    code = sine_cli.main(
        ["synth", "--procedural", "toycar", "--views", "2", "--out", str(tmp_path)]
    )
    assert code == 2
    assert "at least 3" in capsys.readouterr().err
    code = sine_cli.main(
        ["synth", "--procedural", "figurine", "--out", str(tmp_path / "fig"), "--views", "3",
         "--width", "32", "--height", "24", "--quiet"]
    )  # fmt: skip
    assert code == 0 and (tmp_path / "fig" / "images" / "r_002.png").is_file()
    assert (tmp_path / "fig" / "config.yaml").is_file()


def test_material_groups_become_parts(tmp_path):
    (tmp_path / "a.mtl").write_text("newmtl red\nKd 1 0 0\nnewmtl blue\nKd 0 0 1\n")
    (tmp_path / "a.obj").write_text(
        "mtllib a.mtl\nv -1 -1 0\nv 1 -1 0\nv -1 1 0\nv 1 1 0\nv 0 0 1.5\n"
        "usemtl red\nf 1 2 5\nf 2 4 5\nusemtl blue\nf 4 3 5\nf 3 1 5\nf 1 3 2\nf 2 3 4\n"
    )  # a square pyramid: two red sides, two blue sides and a blue base
    out = tmp_path / "out"
    synthesize(
        SynthConfig(
            out=out,
            mesh=tmp_path / "a.obj",
            up_axis="z",
            views=4,
            width=48,
            height=40,
            supersample=1,
        ),
        progress=False,
    )
    parts = {v: int(k) for k, v in json.loads((out / "parts.json").read_text()).items()}
    assert set(parts) == {"red", "blue"}
    for i in range(4):
        labels = read_label_map(out / "labels" / f"r_{i:03d}.png")
        image = read_image(out / "images" / f"r_{i:03d}.png")
        red, blue = labels == parts["red"], labels == parts["blue"]
        assert red.any() and blue.any()
        assert np.all(image[red][:, 0] > image[red][:, 2])
        assert np.all(image[blue][:, 2] > image[blue][:, 0])
