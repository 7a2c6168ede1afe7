"""Ground-truth edits of `sine synth` (recon.synth): the geometric edits (a smooth stretch above a
plane, a part scaled about its centre) and their displacement of any points (`gt_displacement`),
the GT mesh of a geometric edit, the texture edits (recolour, decal, new texture image), part
selection, and the edited meshes and edit.json parameters of a SynthConfig.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from recon.mesh_data import MeshData, plane_side
from recon.synth_mesh import normalised_plane
from render.errors import SineError

if TYPE_CHECKING:
    from recon.synth import SynthConfig

EDIT_KINDS = ("geometric", "texture")
GEOMETRIC_OPERATIONS = ("stretch", "scale_part")  # edit.json: stretch_above_plane, scale_part
TEXTURE_OPERATIONS = ("recolor", "decal")  # edit.json: recolor_part, decal
DECAL_PATTERNS = ("stripes", "checker", "disc")
DECAL_AXES = {"stripes": (0.0, 0.0, 1.0), "disc": (1.0, 0.0, 0.0)}  # default --edit-decal-axis
GT_DISPLACEMENT_FILE = "gt_displacement.npz"  # in a geometric edit's folder
PART_TIE_TOLERANCE = (
    1e-6  # run units: a point this close to the part and another goes with the part
)


# ---- edits --------------------------------------------------------------------------------
def stretch_displacement(points: np.ndarray, plane, scale: float, falloff: float) -> np.ndarray:
    """Displacement [N, 3] of the smooth stretch along the plane normal of the part above it.

    With s the signed distance to the plane, the local stretch factor along n grows from 1 at
    s = 0 to `scale` at s = falloff (smoothstep), so the displacement is (scale - 1) * G(s) * n with
    G(s) = 0 for s <= 0, falloff * (u^3 - u^4 / 2) with u = s / falloff inside the band, and
    s - falloff / 2 beyond it (C2-continuous). Points below the plane do not move.
    """
    plane = normalised_plane(plane)
    s = plane_side(points, plane)
    falloff = max(float(falloff), 1e-9)
    u = np.clip(s / falloff, 0.0, 1.0)
    g = np.where(s >= falloff, s - 0.5 * falloff, falloff * (u**3 - 0.5 * u**4))
    g = np.where(s <= 0, 0.0, g)
    return (scale - 1.0) * g[:, None] * plane[None, :3]


def geometric_edit(mesh: MeshData, plane, scale: float, falloff: float) -> MeshData:
    """The mesh with the part above `plane` stretched along its normal (rest positions kept).

    The faces that reach above the plane are first split into edges of at most
    STRETCH_MAX_EDGE, so the rendered surface follows the smooth stretch inside big faces too
    (a box's side spanning the plane would otherwise stretch uniformly from corner to corner,
    and its texture with it, unlike `stretch_displacement` at the points between)."""
    reach = STRETCH_MAX_EDGE
    mesh = mesh.subdivided(reach, lambda v: plane_side(v, normalised_plane(plane)) > -reach)
    moved = mesh.vertices + stretch_displacement(mesh.vertices, plane, scale, falloff)
    return mesh.replace(vertices=moved)


STRETCH_MAX_EDGE = 0.02  # run units (the object within radius 0.8): edges of a stretched face


def part_vertex_mask(mesh: MeshData, part: int) -> np.ndarray:
    """[V] bool: the vertices that belong to part `part`, for `scale_part_edit`.

    With face parts, the vertices of the part's faces and every vertex at the same position as one
    of them (a vertex shared with another part moves with the part, so the mesh stays connected:
    the other part's faces at the seam stretch); with a plane split (`part_plane`), the vertices
    on the part's side of the plane (rest positions).
    """
    if mesh.part_plane is not None:
        own = mesh.vertex_labels() == int(part)
    else:
        own = np.zeros(len(mesh.vertices), dtype=bool)
        own[mesh.faces[mesh.face_parts == int(part)].ravel()] = True
    shared = np.zeros(int(mesh.weld.max()) + 1 if len(mesh.weld) else 0, dtype=bool)
    shared[mesh.weld[own]] = True
    return shared[mesh.weld]


def part_center(mesh: MeshData, part: int) -> np.ndarray:
    """Centre [3] of the bounding box of part `part`'s vertices (rest positions): independent of
    how finely the part is tessellated, unlike the mean of its vertices."""
    points = mesh.rest_vertices[part_vertex_mask(mesh, part)]
    if not len(points):
        raise SineError(f"part {part} has no vertices")
    return 0.5 * (points.min(axis=0) + points.max(axis=0))


def scale_part_edit(
    mesh: MeshData, part: int, scale: float, center=None
) -> tuple[MeshData, np.ndarray]:
    """The mesh with part `part` scaled by `scale` about `center` (default: `part_center`):
    x' = center + scale * (x - center) for the part's vertices (`part_vertex_mask`), the other
    vertices unchanged (rest positions kept, so textures and labels move with the part).
    Returns (edited mesh, center [3])."""
    center = part_center(mesh, part) if center is None else np.asarray(center, np.float64)
    moves = part_vertex_mask(mesh, part)
    moved = mesh.vertices.copy()
    moved[moves] += (float(scale) - 1.0) * (mesh.vertices[moves] - center)
    return mesh.replace(vertices=moved), center.reshape(3)


@dataclass
class GTMesh:
    """The original mesh a geometric edit was applied to (welded, as `mesh.ply`; run units)."""

    vertices: np.ndarray  # [W, 3] float64, rest positions
    faces: np.ndarray  # [F, 3] int
    face_parts: np.ndarray  # [F] part ids (unused where edit.json has a part_plane)
    displacement: np.ndarray | None = None  # [W, 3] the GT displacement of each vertex


def gt_mesh(mesh: MeshData, edited: MeshData | None = None) -> GTMesh:
    """The welded original mesh (the vertices and order of `mesh.ply`) and, given the edited
    mesh, the displacement of each of its vertices."""
    vertices, faces, first = mesh.welded()
    displacement = None if edited is None else edited.vertices[first] - vertices
    return GTMesh(vertices, faces, mesh.face_parts.copy(), displacement)


def load_gt_edit(edit_dir: str | Path) -> tuple[dict, GTMesh | None]:
    """(edit.json, the GT mesh of `gt_displacement.npz` or None) of an edit folder
    (OUT/edits/KIND), the arguments of `gt_displacement`."""
    from render.io import read_json

    edit_dir = Path(edit_dir)
    if not (edit_dir / "edit.json").is_file():
        raise SineError(f"{edit_dir} has no edit.json (is it a `sine synth` edit folder?)")
    edit = read_json(edit_dir / "edit.json")
    path = edit_dir / GT_DISPLACEMENT_FILE
    if not path.is_file():
        return edit, None
    with np.load(path) as data:
        gt = GTMesh(*(np.asarray(data[k]) for k in ("vertices", "faces", "face_parts")))
        gt.displacement = np.asarray(data["displacement"])
    return edit, gt


def _save_gt_mesh(path: Path, gt: GTMesh) -> None:
    from render.io import atomic_path

    with atomic_path(path) as tmp, open(tmp, "wb") as f:
        np.savez(
            f,
            vertices=gt.vertices,
            faces=gt.faces,
            face_parts=gt.face_parts,
            displacement=gt.displacement,
        )


def gt_part_membership(points: np.ndarray, edit: dict, gt: GTMesh | None) -> np.ndarray:
    """[N] bool: which points move with the part of a `scale_part` edit.

    With a plane split (edit.json `part_plane`): the points on the part's side of the plane.
    Otherwise: a point belongs to the part when the nearest point of the GT surface on the
    part's triangles is no further (within PART_TIE_TOLERANCE) than the nearest on the other
    parts' triangles, i.e. the part of the nearest GT surface point, ties to the part. At the GT
    vertices this is exactly `part_vertex_mask` (a vertex shared with another part moves);
    nearest surface rather than nearest vertex, as a point on a big coarse face (a box's top)
    can be nearer to a vertex of a neighbouring part than to any of its own face's vertices.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    part = int(edit["part"])
    if edit.get("part_plane") is not None:
        side = plane_side(points, edit["part_plane"]) > 0
        return side if part == 2 else ~side
    if gt is None:
        raise SineError(
            "a scale_part edit needs the GT mesh to tell which points belong to the part: "
            "load it with recon.synth_edits.load_gt_edit "
            f"(the edit folder's {GT_DISPLACEMENT_FILE})"
        )
    import open3d as o3d

    query = o3d.core.Tensor(points.astype(np.float32))
    distances = []
    for faces in (gt.faces[gt.face_parts == part], gt.faces[gt.face_parts != part]):
        if not len(faces):
            distances.append(np.full(len(points), np.inf))
            continue
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(gt.vertices.astype(np.float32)),
            o3d.core.Tensor(faces.astype(np.uint32)),
        )
        distances.append(scene.compute_distance(query).numpy().astype(np.float64))
    return distances[0] <= distances[1] + PART_TIE_TOLERANCE


def gt_displacement(points: np.ndarray, edit: dict, gt: GTMesh | None = None) -> np.ndarray:
    """The GT geometric edit's displacement [N, 3] of any points [N, 3] (run units of the synth:
    those of mesh.ply and cameras.json), from edit.json (`edit`) and, for `scale_part`, the GT
    mesh (`load_gt_edit`): points + gt_displacement(points, ...) is where the edit takes them.

    - stretch_above_plane: `stretch_displacement` (defined everywhere);
    - scale_part: (scale - 1) * (p - center) for the points that belong to the part
      (`gt_part_membership`: the part of the nearest GT surface point), 0 elsewhere: the part's
      exact uniform scaling, so a surface near the part (a reconstruction) scales smoothly.
    At the GT mesh's vertices both are exactly the rendered edit's displacement.
    """
    points = np.asarray(points, np.float64).reshape(-1, 3)
    operation = edit.get("operation")
    if operation in ("stretch_above_plane", "stretch"):
        return stretch_displacement(points, edit["plane"], edit["scale"], edit["falloff"])
    if operation == "scale_part":
        inside = gt_part_membership(points, edit, gt)
        center = np.asarray(edit["center"], np.float64).reshape(3)
        out = np.zeros_like(points)
        out[inside] = (float(edit["scale"]) - 1.0) * (points[inside] - center)
        return out
    raise SineError(
        f"edit.json operation {operation!r} is not a geometric edit "
        "(stretch_above_plane or scale_part)"
    )


def make_decal(mesh: MeshData, part: int, pattern: str, colors, size: float, axis=None) -> dict:
    """The decal of `recon.mesh_data.decal_pattern` on part `part`: centred on the part's
    bounding-box centre (`part_center`, rest positions), `axis` defaulting to DECAL_AXES (stripes:
    horizontal bands; disc: on the side facing +x, the first camera's; checker: none)."""
    if pattern not in DECAL_PATTERNS:
        raise SineError(f"unknown decal {pattern!r}; use one of {', '.join(DECAL_PATTERNS)}")
    colors = np.asarray(colors, np.float64).reshape(2, 3)
    if pattern == "checker":
        axis = None
    else:
        axis = np.asarray(DECAL_AXES[pattern] if axis is None else axis, np.float64).reshape(3)
        if np.linalg.norm(axis) < 1e-12:
            raise SineError("--edit-decal-axis needs a non-zero direction")
        axis = (axis / np.linalg.norm(axis)).tolist()
    return {
        "pattern": pattern,
        "colors": colors.tolist(),
        "size": float(size),
        "center": part_center(mesh, part).tolist(),
        "axis": axis,
    }


def texture_edit(
    mesh: MeshData,
    part: int | None = None,
    hue_shift_deg: float = 120.0,
    color=None,
    texture: np.ndarray | None = None,
    decal: dict | None = None,
) -> MeshData:
    """Recolours part `part` (hue rotation, a solid colour, or a `decal`), or swaps every texture
    image."""
    if texture is not None:
        if not mesh.textures:
            raise SineError(
                "--edit-texture needs a mesh with a UV texture (not a procedural object)"
            )
        return mesh.replace(textures=[np.asarray(texture, np.float32)] * len(mesh.textures))
    if part is None:
        raise SineError("a texture edit needs a part id or a texture image")
    if decal is not None:
        return mesh.replace(recolor={"part": int(part), "decal": decal})
    recolor = {
        "part": int(part),
        "hue_shift_deg": float(hue_shift_deg),
        "color": None if color is None else [float(c) for c in color],
        "min_saturation": 0.5,
    }
    return mesh.replace(recolor=recolor)


# ---- the edits of a SynthConfig -----------------------------------------------------------
def _edit_part(cfg: SynthConfig, mesh: MeshData, hints: dict) -> int:
    """--edit-part (or the object's suggestion), checked against the mesh's parts."""
    part = cfg.edit_part if cfg.edit_part is not None else hints.get("edit_part", 1)
    if int(part) not in mesh.part_names:
        raise SineError(
            f"--edit-part {part} is not a part of this object "
            f"(parts: {', '.join(f'{k}={v}' for k, v in mesh.part_names.items())})"
        )
    return int(part)


def _geometric_params(cfg: SynthConfig, mesh: MeshData, hints: dict):
    """(edited mesh, edit.json) of the geometric edit."""
    if cfg.edit_operation == "scale_part":
        part = _edit_part(cfg, mesh, hints)
        edited, center = scale_part_edit(mesh, part, cfg.edit_scale, cfg.edit_pivot)
        params = {
            "kind": "geometric",
            "operation": "scale_part",
            "part": part,
            "part_name": mesh.part_names[part],
            "scale": float(cfg.edit_scale),
            "center": center.tolist(),
            "center_from": "--edit-pivot"
            if cfg.edit_pivot is not None
            else "centre of the bounding box of the part's vertices (rest positions)",
            "part_plane": None if mesh.part_plane is None else mesh.part_plane.tolist(),
            "formula": "x' = center + scale * (x - center) for the part's points, x' = x "
            "elsewhere; see recon.synth_edits.gt_displacement",
            "shared_vertices": "a vertex at the same position as a vertex of the part moves with "
            "the part (the mesh stays connected; the other part's faces at the seam stretch)",
            "membership": "a mesh vertex: it or a vertex at its position is on a face of the part "
            "(with part_plane: on the part's side of the plane, label 2 above, 1 below); any "
            "other point: the part of the nearest GT surface point, ties to the part "
            "(recon.synth_edits.gt_part_membership)",
        }
    else:
        plane = cfg.edit_plane if cfg.edit_plane is not None else hints.get("edit_plane")
        plane = normalised_plane(plane if plane is not None else [0.0, 0.0, 1.0, 0.0])
        edited = geometric_edit(mesh, plane, cfg.edit_scale, cfg.edit_falloff)
        params = {
            "kind": "geometric",
            "operation": "stretch_above_plane",
            "plane": plane.tolist(),
            "plane_convention": "n.x = D with |n| = 1; above: n.x > D (run units)",
            "scale": float(cfg.edit_scale),
            "falloff": float(cfg.edit_falloff),
            "formula": "x' = x + (scale - 1) * G(n.x - D) * n, "
            "see recon.synth_edits.stretch_displacement",
        }
    # the original vertices (a stretch appends the vertices that split its faces)
    moved = np.linalg.norm(edited.vertices[: len(mesh.vertices)] - mesh.vertices, axis=1)
    params.update(
        units="run units of the synth (mesh.ply, cameras.json; synth.json normalization)",
        vertices_moved=int((moved > 0).sum()),
        max_displacement=float(moved.max()),
        gt_displacement_file=GT_DISPLACEMENT_FILE,
        gt_displacement_arrays="vertices [W, 3] and faces [F, 3] of the original mesh.ply "
        "(welded, rest positions), face_parts [F], displacement [W, 3] of each vertex "
        "(recon.synth_edits.load_gt_edit)",
    )
    return edited, params


def _texture_params(cfg: SynthConfig, mesh: MeshData, hints: dict):
    """(edited mesh, edit.json) of the texture edit."""
    if cfg.edit_texture is not None:
        from render.io import read_image

        edited = texture_edit(mesh, texture=read_image(cfg.edit_texture))
        return edited, {
            "kind": "texture",
            "operation": "replace_texture",
            "texture": str(cfg.edit_texture),
        }
    part = _edit_part(cfg, mesh, hints)
    params = {"kind": "texture", "part": part, "part_name": mesh.part_names[part]}
    if cfg.edit_texture_operation == "decal":
        colors = [float(c) for c in cfg.edit_decal_colors]
        decal = make_decal(
            mesh, part, cfg.edit_decal, [colors[:3], colors[3:]], cfg.edit_decal_size,
            cfg.edit_decal_axis,
        )  # fmt: skip
        edited = texture_edit(mesh, part, decal=decal)
        params.update(
            operation="decal",
            decal=decal,
            formula="the part's albedo at a rest-space surface point p becomes "
            "colors[index] where recon.mesh_data.decal_pattern(p, decal) paints (run units)",
        )
    else:
        edited = texture_edit(mesh, part, cfg.edit_hue, cfg.edit_color)
        params.update(
            operation="recolor_part", **{k: v for k, v in edited.recolor.items() if k != "part"}
        )
    return edited, params


def _edited_meshes(
    cfg: SynthConfig, mesh: MeshData, hints: dict
) -> list[tuple[str, MeshData, dict]]:
    edits = []
    for kind in dict.fromkeys(cfg.edit):  # unique, in order
        if kind == "geometric":
            edited, params = _geometric_params(cfg, mesh, hints)
        else:
            edited, params = _texture_params(cfg, mesh, hints)
        edits.append((kind, edited, params))
    return edits
