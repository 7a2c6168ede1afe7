"""`sine synth`'s ground-truth edit kinds: stretches along sideways and tilted planes, one part
scaled about its centre (`scale_part`), two-colour decals on a part, and `gt_displacement`, which
recomputes a geometric edit's displacement from edit.json for any points (the benchmarks' oracle)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from recon.mesh_data import decal_pattern
from recon.procedural import CABIN
from recon.synth import SynthConfig, synthesize
from recon.synth_edits import (
    GT_DISPLACEMENT_FILE,
    gt_displacement,
    load_gt_edit,
    stretch_displacement,
)
from recon.synth_mesh import Normalisation
from render.cameras import load_cameras
from render.errors import SineError
from render.io import read_depth, read_image, read_label_map

TINY = dict(views=4, width=48, height=48, supersample=1)
YELLOW, BLUE = [1.0, 0.85, 0.1], [0.1, 0.2, 0.8]


def _vertices(path: Path) -> np.ndarray:
    import trimesh

    return np.asarray(trimesh.load(str(path), process=False).vertices)


def _normalisation(run: Path) -> Normalisation:
    n = json.loads((run / "synth.json").read_text())["normalization"]
    return Normalisation(np.asarray(n["rotation"]), np.asarray(n["center"]), n["scale"])


def _unproject(cam, depth: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(world points [N, 3] of the pixels with depth > 0, their (row, col) [N, 2])."""
    rows, cols = np.nonzero(depth > 0)
    z = depth[rows, cols].astype(np.float64)
    x = (cols + 0.5 - cam.cx) / cam.fx * z
    y = (rows + 0.5 - cam.cy) / cam.fy * z
    c2w = cam.camera_to_world
    return np.stack([x, y, z], 1) @ c2w[:3, :3].T + c2w[:3, 3], np.stack([rows, cols], 1)


@pytest.fixture(scope="module")
def scaled(tmp_path_factory) -> Path:
    """Toycar: cabin (part 2) scaled by 1.5, or painted with stripes. Ambient light 1
    makes every pixel its albedo, so colours can be compared with the decal's formula."""
    out = tmp_path_factory.mktemp("scaled")
    cfg = SynthConfig(
        out=out,
        procedural="toycar",
        edit=["geometric", "texture"],
        edit_operation="scale_part",
        edit_part=2,  # scaled and painted
        edit_scale=1.5,
        edit_texture_operation="decal",
        edit_decal="stripes",
        edit_decal_colors=YELLOW + BLUE,
        edit_decal_size=0.15,
        ambient=1.0,
        **TINY,
    )
    synthesize(cfg, progress=False)
    return out


@pytest.fixture(scope="module")
def disc(tmp_path_factory) -> Path:
    """Toycar, from the command line: a disc decal on the body's front (+x), seen by r_000 only
    (and obliquely by its neighbours): an edit on one side of the object."""
    import sine_cli

    out = tmp_path_factory.mktemp("disc")
    code = sine_cli.main(
        ["synth", "--procedural", "toycar", "--out", str(out), "--views", "4", "--width", "64",
         "--height", "64", "--supersample", "1", "--ambient", "1", "--edit", "texture",
         "--edit-part", "1", "--edit-texture-operation", "decal", "--edit-decal", "disc",
         "--edit-decal-size", "0.1", "--edit-decal-colors", *map(str, YELLOW + BLUE), "--quiet"]
    )  # fmt: skip
    assert code == 0
    return out


# ---- stretches along any plane ------------------------------------------------------------
def test_sideways_plane_stretch_hand_computed():
    """Plane y = 0.1 (normal +y, given unnormalised): a point above it moves along +y only, by
    (scale - 1) * distance with no falloff, (scale - 1) * (distance - falloff / 2) beyond it."""
    pts = np.array([[0.3, 0.5, -0.2], [-0.4, 0.0, 0.3], [0.0, 0.35, 0.6]])
    d = stretch_displacement(pts, [0.0, 2.0, 0.0, 0.2], scale=1.5, falloff=0.0)
    np.testing.assert_allclose(d[:, [0, 2]], 0.0)
    np.testing.assert_allclose(d[:, 1], [0.5 * 0.4, 0.0, 0.5 * 0.25], atol=1e-8)
    edit = {"operation": "stretch_above_plane", "plane": [0, 1, 0, 0.1], "scale": 1.5}
    d = gt_displacement(pts, {**edit, "falloff": 0.1})
    np.testing.assert_allclose(d[:, 1], [0.5 * 0.35, 0.0, 0.5 * 0.2], atol=1e-12)


def test_tilted_plane_stretch_hand_computed():
    """Plane x + z = 0.1 * sqrt(2) (normal (1, 0, 1) / sqrt(2), D = 0.1): the point (0.4, 0.7,
    0.3) lies 0.7 / sqrt(2) - 0.1 = 0.394975 above it and moves along the normal by
    (2 - 1) * (0.394975 - 0.05) = 0.344975, i.e. 0.243934 in x and in z."""
    pts = np.array([[0.4, 0.7, 0.3], [-0.3, 0.2, 0.1]])
    d = stretch_displacement(pts, [1.0, 0.0, 1.0, 0.1 * np.sqrt(2)], scale=2.0, falloff=0.1)
    np.testing.assert_allclose(d[0], [0.243934, 0.0, 0.243934], atol=1e-6)
    np.testing.assert_allclose(d[1], 0.0)  # below the plane


def test_tilted_plane_synth_moves_along_the_normal(tmp_path):
    out = tmp_path / "tilted"
    plane = [1.0, 0.0, 1.0, 0.2]  # |n| = sqrt(2): the plane x + z = 0.2, i.e. D = 0.1414
    synthesize(
        SynthConfig(
            out=out, procedural="toycar", edit=["geometric"], edit_plane=plane, edit_scale=1.3,
            edit_falloff=0.05, **TINY,
        ),
        progress=False,
    )  # fmt: skip
    edit, gt = load_gt_edit(out / "edits" / "geometric")
    n = np.array([1.0, 0.0, 1.0]) / np.sqrt(2)
    np.testing.assert_allclose(edit["plane"], [*n, 0.2 / np.sqrt(2)])
    before = _vertices(out / "mesh.ply")
    after = _vertices(out / "edits" / "geometric" / "mesh.ply")[: len(before)]  # + split faces
    np.testing.assert_allclose(gt.vertices, before, atol=1e-6)  # the PLY holds float32
    np.testing.assert_allclose(after - before, gt.displacement, atol=1e-6)
    s = before @ n - edit["plane"][3]
    far = s > 0.05
    assert far.sum() >= 4 and (s <= 0).sum() >= 4
    np.testing.assert_allclose(
        (after - before)[far], 0.3 * (s[far] - 0.025)[:, None] * n, atol=1e-6
    )
    np.testing.assert_array_equal(after[s <= -1e-6], before[s <= -1e-6])
    np.testing.assert_allclose(gt_displacement(gt.vertices, edit), gt.displacement, atol=1e-12)
    assert edit["gt_displacement_file"] == GT_DISPLACEMENT_FILE
    assert set(edit["changed_pixels_per_view"]) == {f"r_{i:03d}" for i in range(4)}


# ---- scale one part -----------------------------------------------------------------------
def test_scale_part_scales_the_cabin_about_its_centre(scaled):
    edit, gt = load_gt_edit(scaled / "edits" / "geometric")
    assert edit["operation"] == "scale_part" and edit["part"] == 2 and edit["scale"] == 1.5
    assert edit["part_name"] == "cabin" and edit["part_plane"] is None
    # The centre: the cabin box's centre, brought to run units.
    np.testing.assert_allclose(edit["center"], _normalisation(scaled).apply(CABIN["center"]))
    labels = np.load(scaled / "mesh_vertex_parts.npy")
    before = _vertices(scaled / "mesh.ply")
    after = _vertices(scaled / "edits" / "geometric" / "mesh.ply")
    cabin, center = labels == 2, np.asarray(edit["center"])
    assert cabin.sum() == 8  # a box
    np.testing.assert_allclose(0.5 * (before[cabin].min(0) + before[cabin].max(0)), center)
    np.testing.assert_allclose(0.5 * (after[cabin].min(0) + after[cabin].max(0)), center, atol=1e-6)
    r, r_after = before[cabin] - center, after[cabin] - center
    np.testing.assert_allclose(r_after, 1.5 * r, atol=1e-6)  # distance r -> 1.5 r, same direction
    np.testing.assert_array_equal(after[~cabin], before[~cabin])  # body and wheels stay
    assert edit["vertices_moved"] == 8
    # gt_displacement at the GT vertices: exactly the rendered mesh's displacement
    d = gt_displacement(gt.vertices, edit, gt)
    np.testing.assert_allclose(d, gt.displacement, atol=1e-12)
    np.testing.assert_allclose(gt.displacement, after - before, atol=1e-6)
    assert gt_displacement(center[None], edit, gt) == pytest.approx(np.zeros((1, 3)))


def test_gt_displacement_of_points_off_the_vertices(scaled):
    """A point belongs to the part of the nearest GT surface point: a point on the body's top
    next to the cabin stays although its nearest GT vertex is a cabin corner; points on and just
    off the cabin's side scale with the cabin."""
    edit, gt = load_gt_edit(scaled / "edits" / "geometric")
    norm = _normalisation(scaled)
    body_top = norm.apply([[0.4, 0.3, 0.65]])  # source units: body top z = 0.65, cabin x <= 0.35
    labels = np.load(scaled / "mesh_vertex_parts.npy")
    assert labels[np.argmin(np.linalg.norm(gt.vertices - body_top, axis=1))] == 2
    np.testing.assert_array_equal(gt_displacement(body_top, edit, gt), 0.0)
    cabin_side = norm.apply([[-0.15, 0.4, 0.9], [-0.15, 0.41, 0.9], [0.3, -0.4, 0.7]])
    center = np.asarray(edit["center"])
    np.testing.assert_allclose(
        gt_displacement(cabin_side, edit, gt), 0.5 * (cabin_side - center), atol=1e-12
    )
    wheel = norm.apply([[0.62, 0.52, 0.25]])  # a wheel's outer cap centre
    np.testing.assert_array_equal(gt_displacement(wheel, edit, gt), 0.0)
    with pytest.raises(SineError, match="load_gt_edit"):
        gt_displacement(cabin_side, edit)  # which points are the cabin's needs the GT mesh


def test_scale_part_on_a_plane_split_mesh(tmp_path):
    """A single-material mesh: the part is a side of the plane; arbitrary points go by their side."""
    obj = tmp_path / "tet.obj"
    obj.write_text("v 0 0 -1\nv 1 0 -1\nv 0 1 -1\nv 0 0 1\nf 1 3 2\nf 1 2 4\nf 2 3 4\nf 3 1 4\n")
    out = tmp_path / "out"
    synthesize(
        SynthConfig(
            out=out, mesh=obj, up_axis="z", edit=["geometric"], edit_operation="scale_part",
            edit_part=2, edit_scale=2.0, edit_pivot=[0.0, 0.0, 0.5], **TINY,
        ),
        progress=False,
    )  # fmt: skip
    edit, gt = load_gt_edit(out / "edits" / "geometric")
    assert edit["center"] == [0.0, 0.0, 0.5] and edit["center_from"] == "--edit-pivot"
    assert edit["part_plane"] == [0.0, 0.0, 1.0, 0.0]
    pts = np.array([[0.1, 0.1, 0.2], [0.1, 0.1, -0.2]])
    np.testing.assert_allclose(gt_displacement(pts, edit), [[0.1, 0.1, -0.3], [0.0, 0.0, 0.0]])
    np.testing.assert_allclose(gt_displacement(gt.vertices, edit, gt), gt.displacement, atol=1e-12)
    assert (np.linalg.norm(gt.displacement, axis=1) > 0).sum() == 1  # the apex only


# ---- decals -------------------------------------------------------------------------------
def test_decal_pattern_hand_computed():
    c = [1.0, 0.0, 0.0]
    pts = np.array([[1.0, 0.0, 0.04], [1.0, 0.0, 0.06], [1.0, 5.0, -0.16], [1.0, 0.0, 0.26]])
    stripes = dict(pattern="stripes", center=c, size=0.1, axis=[0, 0, 2.0])
    painted, index = decal_pattern(pts, stripes)
    assert painted.all() and index.tolist() == [0, 1, 0, 1]  # bands [-0.05, 0.05), [0.05, 0.15)
    checker = dict(pattern="checker", center=c, size=0.1, axis=None)
    q = np.array([[1.0, 0.0, 0.0], [1.1, 0.0, 0.0], [1.1, 0.1, 0.0], [1.1, 0.1, 0.1]])
    assert decal_pattern(q, checker)[1].tolist() == [0, 1, 0, 1]
    disc = dict(pattern="disc", center=c, size=0.1, axis=[1.0, 0.0, 0.0])
    d = np.array([[1.5, 0.05, 0.05], [1.5, 0.12, 0.0], [1.5, 0.0, 0.2], [0.5, 0.0, 0.0]])
    painted, index = decal_pattern(d, disc)  # inside r < 0.1, ring to 0.15, front only (+x)
    assert painted.tolist() == [True, True, False, False] and index[:2].tolist() == [0, 1]


def test_stripes_decal_paints_the_part_only_in_two_colours(scaled):
    edit = json.loads((scaled / "edits" / "texture" / "edit.json").read_text())
    assert edit["operation"] == "decal" and edit["part"] == 2 and edit["part_name"] == "cabin"
    decal = edit["decal"]
    assert decal["pattern"] == "stripes" and decal["size"] == 0.15
    assert decal["colors"] == [YELLOW, BLUE] and decal["axis"] == [0.0, 0.0, 1.0]
    geometric = json.loads((scaled / "edits" / "geometric" / "edit.json").read_text())
    np.testing.assert_allclose(decal["center"], geometric["center"])  # the cabin's centre
    colours = set()
    for cam in load_cameras(scaled / "cameras.json").frames:
        stem = Path(cam.name).stem
        labels = read_label_map(scaled / "labels" / f"{stem}.png")
        np.testing.assert_array_equal(
            labels, read_label_map(scaled / "edits" / "texture" / "labels" / f"{stem}.png")
        )
        before = read_image(scaled / "images" / f"{stem}.png")
        after = read_image(scaled / "edits" / "texture" / "images" / f"{stem}.png")
        changed = np.any(before != after, axis=-1)
        assert not changed[labels != 2].any()
        assert changed[labels == 2].mean() > 0.7
        assert edit["changed_pixels_per_view"][stem] == changed.sum()
        assert edit["part_pixels_per_view"][stem] == (labels == 2).sum() > 0
        colours |= {tuple(c) for c in np.round(after[labels == 2] * 255).astype(int).tolist()}
    expected = {tuple(np.round(np.array(c) * 255).astype(int).tolist()) for c in (YELLOW, BLUE)}
    assert colours == expected


def test_decal_colour_is_a_function_of_the_surface_point(scaled):
    """In every view a pixel of the part has the colour the decal gives its 3D point (away from
    the stripes' edges), and points seen in two views have the same colour in both."""
    edit = json.loads((scaled / "edits" / "texture" / "edit.json").read_text())
    decal, colours = edit["decal"], np.array(edit["decal"]["colors"])
    seen = []
    for cam in load_cameras(scaled / "cameras.json").frames:
        stem = Path(cam.name).stem
        labels = read_label_map(scaled / "labels" / f"{stem}.png")
        depth = read_depth(scaled / "edits" / "texture" / "depth" / f"{stem}.npy")
        image = read_image(scaled / "edits" / "texture" / "images" / f"{stem}.png")
        points, pix = _unproject(cam, np.where(labels == 2, depth, 0.0))
        along = (points - decal["center"]) @ np.array(decal["axis"]) / decal["size"] + 0.5
        clear = np.abs(along - np.round(along)) > 0.02
        _, index = decal_pattern(points, decal)
        rgb = image[pix[:, 0], pix[:, 1]]
        np.testing.assert_allclose(rgb[clear], colours[index[clear]], atol=0.6 / 255)
        seen.append((points[clear], rgb[clear]))
    from scipy.spatial import cKDTree

    pairs = 0
    for i in range(len(seen)):
        for j in range(i + 1, len(seen)):
            dist, k = cKDTree(seen[j][0]).query(seen[i][0])
            near = dist < 0.01
            np.testing.assert_array_equal(seen[i][1][near], seen[j][1][k[near]])
            pairs += near.sum()
    assert pairs >= 5


def test_disc_decal_on_one_side(disc):
    edit = json.loads((disc / "edits" / "texture" / "edit.json").read_text())
    assert edit["operation"] == "decal" and edit["part_name"] == "body"
    assert edit["decal"]["pattern"] == "disc" and edit["decal"]["axis"] == [1.0, 0.0, 0.0]
    assert edit["decal"]["colors"] == [YELLOW, BLUE]
    changed = edit["changed_pixels_per_view"]
    assert changed["r_000"] > 20  # facing +x: the car's front
    assert changed["r_002"] == 0  # the back: the disc is not painted there
    assert edit["part_pixels_per_view"]["r_002"] > 0  # although the body is seen
    before = read_image(disc / "images" / "r_000.png")
    after = read_image(disc / "edits" / "texture" / "images" / "r_000.png")
    labels = read_label_map(disc / "labels" / "r_000.png")
    diff = np.any(before != after, axis=-1)
    assert diff.sum() == changed["r_000"] and not diff[labels != 1].any()
    painted = {tuple(c) for c in np.round(after[diff] * 255).astype(int).tolist()}
    assert painted == {tuple(np.round(np.array(c) * 255).astype(int)) for c in (YELLOW, BLUE)}
    synth = json.loads((disc / "synth.json").read_text())["config"]
    assert synth["edit_texture_operation"] == "decal" and synth["edit_decal"] == "disc"


# ---- errors -------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "kwargs, message",
    [
        (dict(edit=["geometric"], edit_operation="twist"), "unknown --edit-operation"),
        (dict(edit=["texture"], edit_texture_operation="paint"), "--edit-texture-operation"),
        (dict(edit=["texture"], edit_decal="logo"), "unknown --edit-decal"),
        (dict(edit=["geometric"], edit_operation="scale_part", edit_part=9), "not a part"),
        (dict(edit=["geometric"], edit_scale=0.0), "positive"),
        (dict(edit=["geometric"], edit_pivot=[0.0, 0.0, 0.0]), "scale_part only"),
        (dict(edit=["geometric"], edit_operation="scale_part", edit_pivot=[0.0]), "X Y Z"),
        (dict(edit=["texture"], edit_decal_colors=[1.0, 0.0, 0.0]), "six numbers"),
        (dict(edit=["texture"], edit_decal_colors=[2.0] * 6), "six numbers"),
        (dict(edit=["texture"], edit_decal_size=0.0), "--edit-decal-size"),
        (dict(edit=["texture"], edit_decal_axis=[0.0, 0.0, 0.0]), "not all zero"),
        (
            dict(edit=["texture"], edit_texture_operation="decal", edit_texture=Path(__file__)),
            "cannot be combined",
        ),
    ],
)
def test_edit_option_errors(tmp_path, kwargs, message):
    cfg = SynthConfig(out=tmp_path / "out", procedural="toycar", **TINY, **kwargs)
    with pytest.raises(SineError, match=message):
        synthesize(cfg, progress=False)
    assert not (tmp_path / "out").exists()  # refused before any work


def test_gt_displacement_refuses_a_texture_edit():
    with pytest.raises(SineError, match="not a geometric edit"):
        gt_displacement(np.zeros((1, 3)), {"operation": "decal"})


def test_another_edit_with_the_cameras_of_an_earlier_capture(scaled, tmp_path):
    cfg = SynthConfig(
        out=tmp_path / "sideways",
        procedural="toycar",
        edit=["geometric"],
        edit_plane=[1.0, 0.0, 0.0, 0.2],
        ambient=1.0,
        cameras_from=scaled,
        **TINY,
    )
    synthesize(cfg, progress=False)
    before = load_cameras(scaled / "cameras.json").frames
    after = load_cameras(tmp_path / "sideways" / "cameras.json").frames
    for a, b in zip(before, after, strict=True):
        np.testing.assert_array_equal(a.camera_to_world, b.camera_to_world)
    for cam in before:  # the same capture: the originals are the same images
        name = Path(cam.name).name
        np.testing.assert_array_equal(
            read_image(scaled / "images" / name),
            read_image(tmp_path / "sideways" / "images" / name),
        )
    wrong = SynthConfig(**{**cfg.__dict__, "out": tmp_path / "w", "views": TINY["views"] + 1})
    with pytest.raises(SineError, match="give the same --views, --width, --height"):
        synthesize(wrong, progress=False)


def _points_on_faces(mesh, n: int = 4000, seed: int = 0):
    """(rendered, rest) positions [n, 3] of random points on the mesh's faces."""
    rng = np.random.default_rng(seed)
    faces = rng.integers(0, len(mesh.faces), n)
    bary = rng.dirichlet([1.0, 1.0, 1.0], n)
    return (
        np.einsum("nk,nkd->nd", bary, mesh.vertices[mesh.faces[faces]]),
        np.einsum("nk,nkd->nd", bary, mesh.rest_vertices[mesh.faces[faces]]),
    )


def test_a_stretch_follows_the_smooth_field_inside_big_faces():
    from recon import procedural
    from recon.synth_edits import STRETCH_MAX_EDGE, geometric_edit, stretch_displacement
    from recon.synth_mesh import normalise

    mesh, _ = normalise(procedural.build("toycar").mesh, "z")
    plane = np.array([0.0, 0.0, 1.0, 0.1])
    edited = geometric_edit(mesh, plane, 1.5, 0.1)
    np.testing.assert_allclose(
        edited.vertices[: len(mesh.vertices)] - mesh.vertices,
        stretch_displacement(mesh.vertices, plane, 1.5, 0.1),
    )
    pos, rest = _points_on_faces(edited)
    error = np.linalg.norm(pos - rest - stretch_displacement(rest, plane, 1.5, 0.1), axis=1)
    assert error.max() < 2e-3  # piecewise linear over edges of STRETCH_MAX_EDGE
    coarse = mesh.replace(
        vertices=mesh.vertices + stretch_displacement(mesh.vertices, plane, 1.5, 0.1)
    )
    pos, rest = _points_on_faces(coarse)
    coarse_error = np.linalg.norm(pos - rest - stretch_displacement(rest, plane, 1.5, 0.1), axis=1)
    assert coarse_error.max() > 0.02  # the cabin's sides, corner to corner
    above = (edited.rest_vertices[edited.faces] @ plane[:3] > plane[3] + STRETCH_MAX_EDGE).all(1)
    tri = edited.rest_vertices[edited.faces[above]]
    assert np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max() <= STRETCH_MAX_EDGE
    labels = np.unique(edited.face_parts)
    np.testing.assert_array_equal(labels, np.unique(mesh.face_parts))


def test_subdivision_carries_uvs_and_vertex_colours():
    from recon.mesh_data import MeshData

    square = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]], float)
    faces = np.array([[0, 1, 2], [1, 3, 2]])
    mesh = MeshData(
        vertices=square,
        faces=faces,
        part_names={1: "all"},
        face_parts=[1, 1],
        vertex_colors=square.astype(np.float32),  # colour = position
        face_uvs=square[faces][..., :2],  # uv = xy
        face_texture=np.zeros(2, np.int64),
        textures=[np.zeros((4, 4, 3), np.float32)],
    )
    fine = mesh.subdivided(0.3, lambda v: v.sum(axis=1) > 1.5)  # the triangle at (1, 1) only
    assert len(fine.faces) > 2 and (fine.faces[0] == faces[0]).all()
    np.testing.assert_allclose(fine.face_uvs, fine.vertices[fine.faces][..., :2], atol=1e-12)
    np.testing.assert_allclose(fine.vertex_colors, fine.vertices, atol=1e-6)
    np.testing.assert_array_equal(fine.vertices[:4], square)
