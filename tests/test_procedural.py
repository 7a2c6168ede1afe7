"""The procedural objects added for the editing benchmarks: the mug (asymmetric: a handle on one
side only) and the chair (thin legs and slats) are valid meshes with their documented parts, and
a tiny `sine synth` of each shows every part."""

from __future__ import annotations

import json

import numpy as np
import pytest

from recon import procedural
from recon.synth import SynthConfig, synthesize
from render.io import read_label_map

PARTS = {
    "mug": {1: "body", 2: "handle", 3: "band"},
    "chair": {1: "seat", 2: "legs", 3: "back"},
}
EDIT_PART = {"mug": "handle", "chair": "seat"}


def _part_vertices(mesh, part: int) -> np.ndarray:
    return mesh.vertices[np.unique(mesh.faces[mesh.face_parts == part])]


@pytest.mark.parametrize("name", ["mug", "chair"])
def test_object_is_a_valid_mesh_with_its_parts(name):
    import trimesh

    assert name in procedural.PROCEDURAL
    obj = procedural.build(name)
    mesh = obj.mesh
    assert mesh.part_names == PARTS[name]
    assert set(np.unique(mesh.face_parts).tolist()) == set(PARTS[name])  # every part has faces
    assert np.isfinite(mesh.vertices).all()
    assert mesh.faces.min() >= 0 and mesh.faces.max() < len(mesh.vertices)
    tri = mesh.vertices[mesh.faces]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    assert area.min() > 1e-8  # no degenerate triangles
    # Each primitive (a connected piece of the welded mesh) is closed, consistently wound, outward.
    vertices, faces, _ = mesh.welded()
    pieces = trimesh.Trimesh(vertices, faces, process=False).split(only_watertight=False)
    assert len(pieces) >= 3
    for piece in pieces:
        assert piece.is_watertight and piece.is_winding_consistent and piece.volume > 0
    assert mesh.vertices[:, 2].min() == pytest.approx(0.0)  # z up, standing on z = 0
    # The suggestions point at real things: a horizontal plane cutting the object, a part.
    n, d = obj.edit_plane[:3], obj.edit_plane[3]
    np.testing.assert_allclose(n, [0.0, 0.0, 1.0])
    assert mesh.vertices[:, 2].min() < d < mesh.vertices[:, 2].max()
    assert mesh.part_names[obj.edit_part] == EDIT_PART[name]
    # Colours: in [0, 1] and textured (not one flat colour) on every part.
    centroids = tri.mean(axis=1)
    colors = mesh.color_fn(centroids, np.arange(len(mesh.faces)))
    assert colors.shape == (len(mesh.faces), 3) and colors.min() >= 0 and colors.max() <= 1
    for part in PARTS[name]:
        assert len(np.unique(colors[mesh.face_parts == part].round(3), axis=0)) >= 2, part


def test_mug_handle_is_on_one_side_only():
    """The handle (its own part) lies on the +x side: every handle vertex has x >= R - wall (in
    the wall or outside the body: none in the cavity, none on the -x half) and |y| <= the tube's
    radius, and it reaches out to x >= R + 0.2 height; every other vertex lies within the band's
    radius of the axis (the rest is a body of revolution). So the mug's extent along +x exceeds
    its extent along -x by more than 0.2 height: it is not mirror symmetric across the plane
    x = 0 (through the axis, perpendicular to the handle's direction)."""
    mesh = procedural.build("mug").mesh
    r, wall, height = procedural.MUG_RADIUS, procedural.MUG_WALL, procedural.MUG_HEIGHT
    handle = _part_vertices(mesh, 2)
    assert handle[:, 0].min() >= r - wall
    assert np.abs(handle[:, 1]).max() <= procedural.HANDLE_MINOR + 1e-9
    assert handle[:, 0].max() >= r + 0.2 * height
    rest = mesh.vertices[np.unique(mesh.faces[mesh.face_parts != 2])]
    assert np.hypot(rest[:, 0], rest[:, 1]).max() <= r + procedural.MUG_BAND["proud"] + 1e-9
    x = mesh.vertices[:, 0]
    assert x.max() - (-x.min()) > 0.2 * height
    # The handle is a loop one can see through: no handle vertex near the middle of its arc.
    hx = handle[:, 0] - (r - procedural.HANDLE_INSET)
    hz = handle[:, 2] - procedural.HANDLE_Z
    assert np.hypot(hx, hz).min() >= procedural.HANDLE_MAJOR - procedural.HANDLE_MINOR - 1e-9


def test_chair_legs_are_thin():
    """Four separate legs, each 4-6 % of the chair's height wide in x and in y, each at least 45 %
    of its height tall; the back's slats are thinner still."""
    mesh = procedural.build("chair").mesh
    height = mesh.vertices[:, 2].max() - mesh.vertices[:, 2].min()
    legs = _part_vertices(mesh, 2)
    quadrant = (legs[:, 0] > 0) * 2 + (legs[:, 1] > 0)
    assert sorted(set(quadrant.tolist())) == [0, 1, 2, 3]
    for q in range(4):
        leg = legs[quadrant == q]
        extent = leg.max(axis=0) - leg.min(axis=0)
        assert 0.04 <= extent[0] / height <= 0.06 and 0.04 <= extent[1] / height <= 0.06
        assert extent[2] / height >= 0.45
    assert procedural.SLAT_WIDTH / height < 0.04


@pytest.mark.parametrize("name", ["mug", "chair"])
def test_tiny_synth_labels_every_part(name, tmp_path):
    """`sine synth --procedural NAME --views 4 --width 48 --height 48 --edit geometric texture`:
    every part is labelled in at least one view, in the original and in both GT edits; the
    texture edit recolours the suggested part."""
    cfg = SynthConfig(
        out=tmp_path, procedural=name, views=4, width=48, height=48, edit=["geometric", "texture"]
    )
    synthesize(cfg, progress=False)
    parts = {int(k): v for k, v in json.loads((tmp_path / "parts.json").read_text()).items()}
    assert parts == PARTS[name]
    for run in (tmp_path, tmp_path / "edits" / "geometric", tmp_path / "edits" / "texture"):
        seen = set()
        for i in range(4):
            seen |= set(np.unique(read_label_map(run / "labels" / f"r_{i:03d}.png")).tolist())
        assert seen == {0, *parts}, run
    edit = json.loads((tmp_path / "edits" / "texture" / "edit.json").read_text())
    assert edit["part_name"] == EDIT_PART[name]
    geometric = json.loads((tmp_path / "edits" / "geometric" / "edit.json").read_text())
    np.testing.assert_allclose(geometric["plane"][:3], [0.0, 0.0, 1.0], atol=1e-9)
    assert geometric["vertices_moved"] > 0
