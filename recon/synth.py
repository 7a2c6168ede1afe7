"""Synthetic turntables with ground truth (DESIGN.md section 4).

A textured mesh (OBJ/GLB/GLTF with a texture image, or a procedural object from
`recon.procedural`) is normalised to run units (centred, bounding-sphere radius ~0.8, up = +z) and
ray cast (render.raycast) from a ring of cameras looking at the origin. Shading is Lambertian +
ambient under a light fixed in the world, so the object's appearance is the same from every view
(what a radiance field can reproduce). Each view gives RGB, mask, camera-z depth and part labels.

Known 3D edits of the same mesh rendered from the same cameras are the ground truth of an edit:
geometric (`--edit-operation`): a smooth stretch of the part above a plane along its normal
(vertical, sideways or tilted, as the plane), or one part scaled uniformly about its centre;
texture (`--edit-texture-operation`): a part recoloured (hue rotation or a colour), a two-colour
decal (stripes, checker or a disc) painted on a part, or a new texture image. Each edit's folder
holds `edit.json` (the operation and every parameter) and, for a geometric edit,
`gt_displacement.npz` (the GT mesh and its displacement per vertex); `gt_displacement` moves any
points by the GT edit (e.g. a reconstructed proxy mesh: an oracle shape prior).

Behind the object (`--background`): a plain colour, a procedural cluttered room (`clutter`: random
coloured shapes, stripes and noise at several scales painted on a large sphere fixed in the world,
so the backdrop moves between views like a real room around a handheld camera) or an image file
(resized to the view, fixed in the image plane like a backdrop behind a turntable). The GT masks
are the object's only.

With `--format nerf-synthetic` the views are also written in the Blender / NeRF-synthetic layout
(`write_nerf_synthetic`), in the `nerf_synthetic/` subfolder (so that the folder holds nothing but
that dataset and `sine ingest` reads its split files).

Planes are given as (nx, ny, nz, D): the points x with n.x = D (n normalised); "above" is n.x > D.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from recon import procedural
from recon.mesh_data import MeshData, plane_side
from recon.mesh_data import sample_texture as sample_texture  # re-exported
from render.cameras import (
    Camera,
    CameraSet,
    cameras_to_transforms,
    load_cameras,
    look_at,
    save_cameras,
)
from render.configs import option, to_dict
from render.errors import SineError
from render.io import (
    write_bytes_atomic,
    write_depth,
    write_image,
    write_json,
    write_label_map,
    write_mask,
)
from render.raycast import MeshRaycaster

OBJECT_RADIUS = 0.8  # bounding-sphere radius of the normalised mesh, run units
DEFAULT_LIGHTS = (  # (direction towards the light, intensity), fixed in the world
    ((0.35, -0.55, 0.76), 0.75),  # key: above, front-right
    ((-0.5, 0.6, 0.3), 0.3),  # fill: the other side
)
UP_AXES = ("auto", "z", "y", "x", "-z", "-y", "-x")
EDIT_KINDS = ("geometric", "texture")
GEOMETRIC_OPERATIONS = ("stretch", "scale_part")  # edit.json: stretch_above_plane, scale_part
TEXTURE_OPERATIONS = ("recolor", "decal")  # edit.json: recolor_part, decal
DECAL_PATTERNS = ("stripes", "checker", "disc")
DECAL_AXES = {"stripes": (0.0, 0.0, 1.0), "disc": (1.0, 0.0, 0.0)}  # default --edit-decal-axis
GT_DISPLACEMENT_FILE = "gt_displacement.npz"  # in a geometric edit's folder
PART_TIE_TOLERANCE = (
    1e-6  # run units: a point this close to the part and another goes with the part
)
OUTPUT_FORMATS = ("sine", "nerf-synthetic")
NERF_SYNTHETIC_DIR = "nerf_synthetic"  # where --format nerf-synthetic writes its layout


# ---- planes -------------------------------------------------------------------------------
def normalised_plane(plane) -> np.ndarray:
    """(n, D) with |n| = 1 describing the same plane."""
    plane = np.asarray(plane, dtype=np.float64).reshape(4)
    norm = np.linalg.norm(plane[:3])
    if norm < 1e-12:
        raise SineError("a plane needs a non-zero normal (NX NY NZ D)")
    return plane / norm


# ---- loading and normalising --------------------------------------------------------------
def up_rotation(up_axis: str) -> np.ndarray:
    """Rotation [3, 3] taking the given axis of the source to +z (right-handed)."""
    rotations = {
        "z": np.eye(3),
        "-z": np.diag([1.0, -1.0, -1.0]),
        "y": np.array([[1.0, 0, 0], [0, 0, -1], [0, 1, 0]]),  # y -> z, z -> -y
        "-y": np.array([[1.0, 0, 0], [0, 0, 1], [0, -1, 0]]),
        "x": np.array([[0, 0, -1.0], [0, 1, 0], [1, 0, 0]]),  # x -> z
        "-x": np.array([[0, 0, 1.0], [0, 1, 0], [-1, 0, 0]]),
    }
    if up_axis not in rotations:
        raise SineError(f"unknown --up-axis {up_axis!r}; use one of {', '.join(UP_AXES)}")
    return rotations[up_axis]


def resolve_up_axis(up_axis: str, path: Path | None) -> str:
    """'auto': y-up for OBJ/GLTF/GLB (their usual convention), z-up otherwise."""
    if up_axis != "auto":
        return up_axis
    if path is not None and path.suffix.lower() in (".obj", ".gltf", ".glb"):
        return "y"
    return "z"


def _pil_to_float(image) -> np.ndarray:
    return np.asarray(image.convert("RGB"), dtype=np.float32) / 255.0


def load_mesh_file(path: str | Path) -> MeshData:
    """Reads a mesh (OBJ + MTL texture, GLB/GLTF, PLY, ...) with trimesh -> MeshData (source units).

    Every geometry/material group becomes one part (named after it).
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise SineError(f"mesh {path} does not exist")
    try:
        loaded = trimesh.load(str(path), process=False)
    except Exception as exc:  # trimesh raises many kinds
        raise SineError(f"cannot read {path} as a mesh ({type(exc).__name__}: {exc})") from None
    if isinstance(loaded, trimesh.Scene):
        geoms = [g for g in loaded.dump(concatenate=False) if isinstance(g, trimesh.Trimesh)]
        names = []
        for g in geoms:
            name = g.metadata.get("name") or g.metadata.get("node") or ""
            names.append(str(name))
    elif isinstance(loaded, trimesh.Trimesh):
        geoms, names = [loaded], [path.stem]
    else:
        geoms, names = [], []
    geoms_names = [(g, n) for g, n in zip(geoms, names, strict=True) if len(g.faces)]
    if not geoms_names:
        raise SineError(f"{path} contains no triangles (is it a point cloud or empty?)")

    verts, faces, parts, colors, uvs, face_tex, textures = [], [], [], [], [], [], []
    part_names: dict[int, str] = {}
    offset = 0
    for k, (g, name) in enumerate(geoms_names):
        v = np.asarray(g.vertices, dtype=np.float64)
        f = np.asarray(g.faces, dtype=np.int64)
        color = np.full((len(v), 3), 0.7, dtype=np.float32)
        corner_uv = np.zeros((len(f), 3, 2))
        tex_id = -1
        visual = g.visual
        if isinstance(visual, trimesh.visual.TextureVisuals):
            mat = visual.material
            if isinstance(mat, trimesh.visual.material.PBRMaterial):
                mat = mat.to_simple()
            image = getattr(mat, "image", None)
            if image is not None and visual.uv is not None and len(visual.uv) == len(v):
                textures.append(_pil_to_float(image))
                tex_id = len(textures) - 1
                corner_uv = np.asarray(visual.uv, dtype=np.float64)[f]
            else:
                diffuse = np.asarray(getattr(mat, "diffuse", [178, 178, 178, 255]), np.float32)
                color[:] = diffuse[:3] / 255.0
        elif getattr(visual, "kind", None) == "vertex":
            color = np.asarray(visual.vertex_colors, np.float32)[:, :3] / 255.0
        elif getattr(visual, "kind", None) == "face":
            fc = np.asarray(visual.face_colors, np.float32)[:, :3] / 255.0
            color[f.ravel()] = np.repeat(fc, 3, axis=0)
        verts.append(v)
        faces.append(f + offset)
        colors.append(color)
        uvs.append(corner_uv)
        face_tex.append(np.full(len(f), tex_id, dtype=np.int64))
        parts.append(np.full(len(f), k + 1, dtype=np.int64))
        part_names[k + 1] = name or f"part{k + 1}"
        offset += len(v)
    return MeshData(
        vertices=np.concatenate(verts),
        faces=np.concatenate(faces),
        part_names=part_names,
        face_parts=np.concatenate(parts),
        vertex_colors=np.concatenate(colors),
        face_uvs=np.concatenate(uvs),
        face_texture=np.concatenate(face_tex),
        textures=textures,
    )


@dataclass
class Normalisation:
    """x_run = scale * (rotation @ x_src - center)."""

    rotation: np.ndarray  # [3, 3]
    center: np.ndarray  # [3]
    scale: float

    def apply(self, points: np.ndarray) -> np.ndarray:
        return self.scale * (np.asarray(points) @ self.rotation.T - self.center)

    def invert(self, points: np.ndarray) -> np.ndarray:
        return (np.asarray(points) / self.scale + self.center) @ self.rotation

    def plane_to_run(self, plane) -> np.ndarray:
        """A source-space plane (n, D) -> the same plane in run units."""
        plane = normalised_plane(plane)
        n = self.rotation @ plane[:3]
        return np.array([*n, self.scale * (plane[3] - n @ self.center)])

    def to_dict(self) -> dict:
        return {
            "formula": "x_run = scale * (rotation @ x_src - center)",
            "rotation": self.rotation.tolist(),
            "center": self.center.tolist(),
            "scale": float(self.scale),
        }


def normalise(mesh: MeshData, up_axis: str = "z", radius: float = OBJECT_RADIUS):
    """Rotates `up_axis` to +z, centres the bounding box at the origin and scales the bounding
    sphere (about that centre) to `radius`. Returns (normalised MeshData, Normalisation)."""
    rotation = up_rotation(up_axis)
    rotated = mesh.vertices @ rotation.T
    used = rotated[np.unique(mesh.faces)]
    center = 0.5 * (used.min(axis=0) + used.max(axis=0))
    extent = np.linalg.norm(used - center, axis=1).max()
    if not np.isfinite(extent) or extent <= 0:
        raise SineError("the mesh is degenerate (all vertices at one point)")
    norm = Normalisation(rotation, center, radius / extent)
    color_fn = None
    if mesh.color_fn is not None:
        source_fn = mesh.color_fn

        def color_fn(points, face_ids):  # procedural colours are defined in source units
            return source_fn(norm.invert(points), face_ids)

    out = mesh.replace(
        vertices=norm.apply(mesh.vertices),
        rest_vertices=norm.apply(mesh.rest_vertices),
        color_fn=color_fn,
        part_plane=None if mesh.part_plane is None else norm.plane_to_run(mesh.part_plane),
    )
    return out, norm


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
            f"load it with recon.synth.load_gt_edit (the edit folder's {GT_DISPLACEMENT_FILE})"
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


# ---- cameras ------------------------------------------------------------------------------
def focal_from_fov(width: int, height: int, fov_deg: float) -> float:
    """Focal length in pixels giving `fov_deg` across the shorter image side."""
    return 0.5 * min(width, height) / np.tan(0.5 * np.radians(fov_deg))


def camera_distance(object_radius: float, fov_deg: float, fill: float = 0.7) -> float:
    """Distance at which a sphere of `object_radius` spans `fill` of the shorter image side."""
    half = np.arctan(fill * np.tan(0.5 * np.radians(fov_deg)))
    return float(object_radius / np.sin(half))


def fit_camera_distance(
    points: np.ndarray,
    n: int,
    width: int,
    height: int,
    elevations_deg=(20.0,),
    fov_deg: float = 40.0,
    fill: float = 0.7,
    max_points: int = 20000,
) -> float:
    """Ring radius at which the points [N, 3] span `fill` of the half-frame (from the image
    centre, horizontally and vertically) in the view where they extend furthest."""
    points = np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(points) > max_points:
        points = points[np.linspace(0, len(points) - 1, max_points).astype(np.int64)]
    radius = float(np.linalg.norm(points, axis=1).max())
    distance = camera_distance(radius, fov_deg, fill)  # bounding sphere: an upper bound
    for _ in range(8):  # fixed point on the (nearly 1/distance) extent; converges in a few steps
        extent = 0.0
        for cam in ring_cameras(n, width, height, elevations_deg, distance, fov_deg):
            uv, z = cam.project(points)
            if (z <= 0).any():
                break
            du = np.abs(uv[:, 0] - cam.cx) / (0.5 * width)
            dv = np.abs(uv[:, 1] - cam.cy) / (0.5 * height)
            extent = max(extent, float(du.max()), float(dv.max()))
        else:
            new = max(distance * extent / fill, 1.05 * radius)
            if abs(new - distance) < 1e-4 * distance:
                return new
            distance = new
            continue
        return camera_distance(radius, fov_deg, fill)  # a camera inside the object: be safe
    return distance


def ring_cameras(
    n: int,
    width: int,
    height: int,
    elevations_deg=(20.0,),
    radius: float = 3.0,
    fov_deg: float = 40.0,
    test_every: int = 8,
) -> list[Camera]:
    """`n` cameras on rings around +z looking at the origin (image up ~ +z).

    Views are split into contiguous blocks, one ring per elevation, azimuths evenly spaced (rings
    interleaved). Every `test_every`-th view (1-based: r_007, r_015, ...) has split "test",
    the same rule as `sine ingest` (recon.ingest.assign_splits), so held-out views agree.
    """
    from recon.ingest import assign_splits

    elevations = [float(e) for e in elevations_deg] or [20.0]
    if n < len(elevations):
        raise SineError(f"{n} views cannot cover {len(elevations)} elevations")
    f = focal_from_fov(width, height, fov_deg)
    cams = []
    splits = assign_splits(n, test_every)
    blocks = np.array_split(np.arange(n), len(elevations))
    for ring, (elev, block) in enumerate(zip(elevations, blocks, strict=True)):
        m = len(block)
        for j, i in enumerate(block):
            az = 2 * np.pi * (j + ring / len(elevations)) / m
            el = np.radians(elev)
            eye = radius * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            cams.append(
                Camera(
                    width,
                    height,
                    f,
                    f,
                    width / 2.0,
                    height / 2.0,
                    camera_to_world=look_at(eye, np.zeros(3)),
                    name=f"r_{i:03d}.png",
                    split=splits[i],
                )
            )
    return cams


# ---- backdrops ----------------------------------------------------------------------------
BACKDROP_SPHERE = 4.0  # radius of the clutter sphere, in camera distances (cameras well inside)
CLUTTER_TEXTURE = (1024, 2048)  # equirectangular texture of the clutter sphere (rows, columns)


@dataclass
class Backdrop:
    """What the cameras see where the object is not: one of a colour [3], an equirectangular
    texture [H, W, 3] on a sphere of `radius` around the origin (fixed in the world) or an image
    [H, W, 3] fixed in the image plane (resized to each view)."""

    colour: np.ndarray | None = None
    texture: np.ndarray | None = None
    radius: float = 0.0
    image: np.ndarray | None = None

    def pixels(self, cam: Camera, rays: np.ndarray) -> np.ndarray:
        """Backdrop RGB [H*W, 3] float32 of the rays [H*W, 6] through `cam`'s pixels."""
        h, w = cam.height, cam.width
        if self.image is not None:
            img = cv2.resize(self.image, (w, h), interpolation=cv2.INTER_AREA)
            return np.ascontiguousarray(img, np.float32).reshape(h * w, 3).copy()
        if self.texture is None:
            colour = np.asarray(self.colour, np.float32).reshape(3)
            return np.broadcast_to(colour, (h * w, 3)).copy()
        o, d = rays[:, :3].astype(np.float64), rays[:, 3:].astype(np.float64)
        od = np.einsum("nd,nd->n", o, d)
        t = -od + np.sqrt(od**2 - np.einsum("nd,nd->n", o, o) + self.radius**2)
        p = o + t[:, None] * d  # [N, 3] on the sphere
        th, tw = self.texture.shape[:2]
        lon = np.arctan2(p[:, 1], p[:, 0])
        lat = np.arcsin(np.clip(p[:, 2] / self.radius, -1.0, 1.0))
        u = ((lon / (2 * np.pi) + 0.5) * tw - 0.5).astype(np.float32)
        v = ((0.5 - lat / np.pi) * th - 0.5).astype(np.float32)
        out = cv2.remap(
            self.texture,
            u.reshape(h, w),
            v.reshape(h, w),
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_WRAP,
        )
        return out.reshape(h * w, 3).astype(np.float32)


def clutter_texture(seed: int = 0, shape: tuple[int, int] = CLUTTER_TEXTURE) -> np.ndarray:
    """A cluttered room as an equirectangular texture [H, W, 3] float32 in [0, 1]: smooth colour
    noise, then hundreds of random shapes (boxes, discs, stripes, lines, checkers) from large to
    small in random colours, then fine grain. Deterministic for a seed."""
    rng = np.random.default_rng(seed)
    h, w = shape
    base = rng.uniform(0.15, 0.85, (4, 8, 3)).astype(np.float32)
    img = cv2.resize(base, (w, h), interpolation=cv2.INTER_CUBIC)
    img = (np.clip(img, 0, 1) * 255).astype(np.uint8)

    def pick() -> tuple[int, ...]:  # muted more often than vivid, like furniture and walls
        grey, vivid = rng.uniform(40, 220), rng.uniform(0, 256, 3)
        return tuple(int(c) for c in grey + rng.uniform(0.2, 1.0) * (vivid - grey))

    for scale in (0.25, 0.12, 0.06, 0.03, 0.015):
        for _ in range(int(6 / scale)):
            colour = pick()
            cx, cy = int(rng.integers(0, w)), int(rng.integers(0, h))
            sx, sy = (rng.uniform(0.3, 1.0, 2) * scale * h).astype(int) + 2
            kind = rng.integers(0, 5)
            if kind == 0:
                cv2.rectangle(img, (cx - sx, cy - sy), (cx + sx, cy + sy), colour, -1)
            elif kind == 1:
                angle = float(rng.uniform(0, 180))
                cv2.ellipse(img, (cx, cy), (int(sx), int(sy)), angle, 0, 360, colour, -1)
            elif kind == 2:  # stripes
                other = pick()
                step = max(2, int(sx) // 3)
                for k, x in enumerate(range(cx - sx, cx + sx, step)):
                    cv2.rectangle(
                        img, (x, cy - sy), (x + step - 1, cy + sy), (colour, other)[k % 2], -1
                    )
            elif kind == 3:
                end = (cx + int(rng.integers(-4, 5)) * sx, cy + int(rng.integers(-4, 5)) * sy)
                cv2.line(img, (cx, cy), end, colour, max(1, int(sy) // 4))
            else:  # checker
                other = pick()
                step = max(2, int(sx) // 2)
                for i, y in enumerate(range(cy - sy, cy + sy, step)):
                    for j, x in enumerate(range(cx - sx, cx + sx, step)):
                        c = (colour, other)[(i + j) % 2]
                        cv2.rectangle(img, (x, y), (x + step - 1, y + step - 1), c, -1)
    out = img.astype(np.float32) / 255.0
    out += rng.normal(0.0, 0.03, out.shape).astype(np.float32)  # grain
    return np.clip(out, 0.0, 1.0)


def parse_background(words) -> tuple[str, object]:
    """--background words -> ("colour", RGB [3]) | ("clutter", None) | ("image", Path)."""
    words = [str(w) for w in words]
    if len(words) == 1 and words[0].lower() == "clutter":
        return "clutter", None
    if len(words) == 3:
        try:
            rgb = np.array([float(x) for x in words])
        except ValueError:
            rgb = None
        if rgb is not None:
            if not np.all((rgb >= 0) & (rgb <= 1)):
                raise SineError("--background R G B: each value must be in [0, 1]")
            return "colour", rgb
    if len(words) == 1:
        path = Path(words[0])
        if not path.is_file():
            raise SineError(
                f"--background {words[0]}: no such image file; use three numbers R G B in [0, 1], "
                "clutter, or the path of an image"
            )
        return "image", path
    raise SineError(
        "--background takes three numbers R G B in [0, 1], the word clutter, or an image path"
    )


def make_backdrop(words, seed: int, camera_distance: float) -> Backdrop:
    """The Backdrop of a --background value (see `parse_background`)."""
    kind, value = parse_background(words)
    if kind == "colour":
        return Backdrop(colour=np.asarray(value, np.float32))
    if kind == "clutter":
        return Backdrop(texture=clutter_texture(seed), radius=BACKDROP_SPHERE * camera_distance)
    from render.io import read_image

    try:
        image = read_image(value)
    except Exception as exc:  # unreadable / not an image
        raise SineError(f"--background {value}: cannot read it as an image ({exc})") from None
    return Backdrop(image=np.ascontiguousarray(image[..., :3], np.float32))


# ---- rendering ----------------------------------------------------------------------------
def _camera_rays(cam: Camera, cache: dict) -> tuple[np.ndarray, np.ndarray]:
    """Rays [H*W, 6] (origin, unit direction; float32) through the pixel centres of `cam`, and
    camera z per unit distance [H*W]. Same maths as Camera.rays, with the camera-frame directions
    cached per intrinsics and rotated by einsum (much faster than a BLAS matmul here)."""
    key = (cam.width, cam.height, cam.fx, cam.fy, cam.cx, cam.cy)
    if key not in cache:
        pix = cam.pixel_grid()
        d = np.stack(
            [(pix[:, 0] - cam.cx) / cam.fx, (pix[:, 1] - cam.cy) / cam.fy, np.ones(len(pix))], 1
        )
        cache[key] = d / np.linalg.norm(d, axis=1, keepdims=True)  # [N, 3] unit, camera frame
    d_cam = cache[key]
    rays = np.empty((len(d_cam), 6), np.float32)
    rays[:, :3] = cam.center
    rays[:, 3:] = np.einsum("nk,dk->nd", d_cam, cam.camera_to_world[:3, :3])
    return rays, d_cam[:, 2].astype(np.float32)


def render_views(
    mesh: MeshData,
    cameras: list[Camera],
    background=(1.0, 1.0, 1.0),
    lights=DEFAULT_LIGHTS,
    ambient: float = 0.35,
    progress: bool = False,
    supersample: int = 1,
) -> list[dict]:
    """Ray casts `mesh` from each camera -> per view dict(rgb [H,W,3] float32, mask [H,W] bool,
    depth [H,W] float32 camera z (0 = background), labels [H,W] int part ids (0 = background)).

    `background`: an RGB colour or a `Backdrop`. `supersample` (odd): rgb is the mean of
    supersample x supersample rays spread over each pixel (a camera pixel integrates the light
    over its area; one ray per pixel aliases fine texture); mask, depth and labels come from the
    centre ray, i.e. the pixel centre, as with one ray."""
    from tqdm import tqdm

    if supersample < 1 or supersample % 2 == 0:
        raise SineError(f"supersample must be an odd number >= 1 (got {supersample})")
    caster = MeshRaycaster((mesh.vertices, mesh.faces))
    face_n, vert_n = mesh.normals()
    light_dirs = np.array([np.asarray(d) / np.linalg.norm(d) for d, _ in lights], np.float32)
    light_power = np.array([p for _, p in lights], np.float32)
    backdrop = background if isinstance(background, Backdrop) else Backdrop(colour=background)
    views, cache = [], {}
    for cam in tqdm(cameras, desc="render", unit="view", disable=not progress):
        s = supersample
        h, w = cam.height, cam.width
        fine = cam.resized(w * s, h * s) if s > 1 else cam
        rays, z_per_t = _camera_rays(fine, cache)
        dirs = rays[:, 3:]
        hits = caster.cast(rays[:, :3], dirs)
        t, mask = hits.t, hits.hit
        fid = hits.triangle[mask]
        uv = hits.uv[mask].astype(np.float64)
        bary = np.stack([1.0 - uv[:, 0] - uv[:, 1], uv[:, 0], uv[:, 1]], axis=1)  # [N, 3]
        rest = mesh.rest_points(fid, bary)
        labels = mesh.labels_at(fid, rest)
        albedo = mesh.albedo_at(fid, bary, rest)  # [N, 3]
        # Shading normal: interpolated on smooth faces, flat elsewhere; facing the camera.
        fn = face_n[fid]
        n = np.where(
            mesh.face_smooth[fid, None], np.einsum("nk,nkd->nd", bary, vert_n[mesh.faces[fid]]), fn
        )
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
        flip = np.einsum("nd,nd->n", fn, dirs[mask]) > 0
        n[flip] *= -1
        cosines = np.einsum("nd,ld->nl", n.astype(np.float32), light_dirs)  # [N, lights]
        diffuse = np.einsum("nl,l->n", np.clip(cosines, 0, None), light_power)  # [N]
        shade = np.clip(ambient + (1 - ambient) * diffuse, 0, 1.2)[:, None]

        rgb = backdrop.pixels(fine, rays)
        rgb[mask] = np.clip(albedo * shade, 0, 1)
        depth = np.zeros(len(rays), np.float32)
        depth[mask] = t[mask] * z_per_t[mask]
        lab = np.zeros(len(rays), np.int64)
        lab[mask] = labels
        # [H, s, W, s, ...]: each pixel's s x s rays; the centre one sits on the pixel centre
        rgb = rgb.reshape(h, s, w, s, 3).mean(axis=(1, 3), dtype=np.float64).astype(np.float32)
        c = s // 2
        views.append(
            {
                "rgb": rgb,
                "mask": mask.reshape(h, s, w, s)[:, c, :, c],
                "depth": depth.reshape(h, s, w, s)[:, c, :, c],
                "labels": lab.reshape(h, s, w, s)[:, c, :, c],
            }
        )
    return views


def write_views(out_dir: Path, cameras: list[Camera], views: list[dict], mesh: MeshData) -> dict:
    """Writes images/, masks/, depth/, labels/, transforms.json, cameras.json, mesh.ply, parts.json."""
    import trimesh  # noqa: F401  (PLY export)

    out_dir = Path(out_dir)
    for sub in ("images", "masks", "depth", "labels"):
        (out_dir / sub).mkdir(parents=True, exist_ok=True)
        for stale in (out_dir / sub).glob("r_*.*"):  # a previous run with more views
            stale.unlink()
    paths = []
    for cam, view in zip(cameras, views, strict=True):
        stem = Path(cam.name).stem
        write_image(out_dir / "images" / f"{stem}.png", view["rgb"])
        write_mask(out_dir / "masks" / f"{stem}.png", view["mask"])
        write_depth(out_dir / "depth" / f"{stem}.npy", view["depth"])
        write_label_map(out_dir / "labels" / f"{stem}.png", view["labels"])
        paths.append(f"images/{stem}.png")
    transforms = cameras_to_transforms(cameras, paths)
    for frame, cam in zip(transforms["frames"], cameras, strict=True):
        stem = Path(cam.name).stem
        frame["mask_path"] = f"masks/{stem}.png"
        frame["depth_file_path"] = f"depth/{stem}.npy"
        frame["label_path"] = f"labels/{stem}.png"
        frame["split"] = cam.split
    transforms["ply_file_path"] = "mesh.ply"
    transforms["depth_unit_scale_factor"] = 1.0
    write_json(out_dir / "transforms.json", transforms)
    save_cameras(
        out_dir / "cameras.json",
        CameraSet(frames=cameras, extra={"source": "sine synth", "depth": "camera z, run units"}),
    )
    write_json(out_dir / "parts.json", {str(k): v for k, v in sorted(mesh.part_names.items())})
    tm = mesh.to_trimesh()
    from render.io import atomic_path

    with atomic_path(out_dir / "mesh.ply") as tmp:
        tm.export(str(tmp), file_type="ply")
    with atomic_path(out_dir / "mesh_vertex_parts.npy") as tmp, open(tmp, "wb") as f:
        np.save(f, mesh.welded_vertex_labels().astype(np.uint16))
    coverage = float(np.mean([v["mask"].mean() for v in views]))
    return {"views": len(views), "mean_mask_coverage": coverage, "mesh_vertices": len(tm.vertices)}


def write_nerf_synthetic(out_dir: Path, cameras: list[Camera], views: list[dict]) -> dict:
    """Writes the views in the Blender / NeRF-synthetic layout into `out_dir`.

    - `train/<stem>.png`, `test/<stem>.png`: 8-bit RGBA, alpha = the object mask (255 / 0), RGB
      the object's colour (straight, not premultiplied), 0 on background pixels;
    - `transforms_train.json`, `transforms_test.json`: `camera_angle_x` (horizontal field of view
      in radians; square pixels, principal point at the image centre, as the Blender data) and per
      frame `file_path` without extension (`./train/r_000`) and `transform_matrix` (camera-to-
      world, OpenGL axes);
    - `transforms_val.json`: the test views again (the same files): the held-out views are
      `sine ingest`'s split rule (every 8th view), and ingest does not count them twice.
    Returns {"train": n, "test": n, "val": n}.
    """
    out_dir = Path(out_dir)
    fx = cameras[0].fx
    for cam in cameras:
        centred = abs(cam.cx - cam.width / 2) < 1e-9 and abs(cam.cy - cam.height / 2) < 1e-9
        if abs(cam.fy - cam.fx) > 1e-9 * cam.fx or abs(cam.fx - fx) > 1e-9 * fx or not centred:
            raise SineError("the NeRF-synthetic format needs one centred square-pixel camera")
    angle = float(2.0 * np.arctan(0.5 * cameras[0].width / fx))
    gl = cameras_to_transforms(cameras, [cam.name for cam in cameras])["frames"]
    frames: dict[str, list[dict]] = {"train": [], "test": []}
    for split in frames:
        (out_dir / split).mkdir(parents=True, exist_ok=True)
        for stale in (out_dir / split).glob("r_*.png"):  # a previous run with more views
            stale.unlink()
    for cam, view, frame in zip(cameras, views, gl, strict=True):
        split = "test" if cam.split == "test" else "train"
        stem = Path(cam.name).stem
        rgba = np.zeros((cam.height, cam.width, 4), np.uint8)
        rgb = (np.clip(view["rgb"], 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)  # as write_image
        rgba[..., :3] = np.where(view["mask"][..., None], rgb, 0)
        rgba[..., 3] = np.where(view["mask"], 255, 0)
        ok, buf = cv2.imencode(".png", rgba[..., [2, 1, 0, 3]])  # RGBA -> BGRA
        if not ok:
            raise SineError(f"cannot encode {out_dir / split / stem}.png")
        write_bytes_atomic(out_dir / split / f"{stem}.png", buf.tobytes())
        frames[split].append(
            {"file_path": f"./{split}/{stem}", "transform_matrix": frame["transform_matrix"]}
        )
    frames["val"] = frames["test"]
    for split, split_frames in frames.items():
        write_json(
            out_dir / f"transforms_{split}.json",
            {"camera_angle_x": angle, "frames": split_frames},
        )
    return {split: len(split_frames) for split, split_frames in frames.items()}


# ---- the whole command --------------------------------------------------------------------
@dataclass
class SynthConfig:
    """`sine synth`: a synthetic turntable with ground truth from a mesh or a procedural object."""

    out: Path = option(Path("synth_out"), "output directory (created; re-running overwrites)")
    mesh: Path | None = option(None, "textured mesh to render (OBJ+MTL+texture, GLB, GLTF, PLY)")
    procedural: str | None = option(
        None,
        f"built-in procedural object instead of --mesh ({', '.join(procedural.PROCEDURAL)})",
    )
    views: int = option(36, "number of views on the camera ring(s) (>= 3)")
    width: int = option(320, "image width in pixels")
    height: int = option(240, "image height in pixels")
    elevation: list[float] = option(
        [20.0], "camera elevation(s) in degrees above the horizon; views are split over them"
    )
    fov: float = option(40.0, "field of view in degrees across the shorter image side")
    fill: float = option(
        0.7,
        "fraction of the half-frame (from the image centre) the object spans in its widest view",
    )
    background: list[str] = option(
        [1.0, 1.0, 1.0],
        "what lies behind the object: a colour R G B in [0, 1]; clutter = a procedural cluttered "
        "room on a large sphere fixed in the world (it moves between views; see "
        "--background-seed); or the path of an image (resized to the view, fixed in the image)",
    )
    background_seed: int = option(0, "random seed of --background clutter", low=0)
    up_axis: str = option(
        "auto",
        "axis of the source mesh that points up (rotated to +z); auto = y for OBJ/GLTF/GLB",
        choices=list(UP_AXES),
    )
    parts_plane: list[float] | None = option(
        None,
        "split a single-material mesh into parts by the plane NX NY NZ D (n.x = D, run units): "
        "label 1 below, 2 above; if omitted, the horizontal plane through the middle",
    )
    ambient: float = option(
        0.35, "ambient light fraction (the rest is the fixed Lambertian lights)"
    )
    edit: list[str] = option(
        [], "ground-truth edits to render beside the originals", choices=list(EDIT_KINDS)
    )
    edit_operation: str = option(
        "stretch",
        "geometric edit: stretch = stretch the part above --edit-plane along the plane's normal "
        "(a horizontal plane: vertical; a vertical plane: sideways; any other: tilted); "
        "scale_part = scale the part --edit-part uniformly by --edit-scale about --edit-pivot, the "
        "other parts unchanged (a vertex shared with another part moves with the part)",
        choices=list(GEOMETRIC_OPERATIONS),
    )
    edit_plane: list[float] | None = option(
        None,
        "geometric edit: stretch the part above the plane NX NY NZ D (run units) along its normal; "
        "if omitted, the object's suggestion (procedural) or the horizontal plane z = 0",
    )
    edit_scale: float = option(
        1.5, "geometric edit: stretch factor along the plane normal, or scale_part's factor (> 0)"
    )
    edit_falloff: float = option(
        0.1, "geometric edit: width (run units) over which the stretch ramps up above the plane"
    )
    edit_pivot: list[float] | None = option(
        None,
        "geometric edit scale_part: the point X Y Z (run units) that stays fixed; if omitted, the "
        "centre of the part's bounding box",
    )
    edit_part: int | None = option(
        None,
        "part id (parts.json) that scale_part scales and the texture edit paints; if omitted, "
        "2 (above) for meshes, the object's suggestion for procedural objects",
    )
    edit_texture_operation: str = option(
        "recolor",
        "texture edit: recolor = rotate the part's hue by --edit-hue (or paint it --edit-color); "
        "decal = paint the two-colour pattern --edit-decal on the part",
        choices=list(TEXTURE_OPERATIONS),
    )
    edit_decal: str = option(
        "stripes",
        "texture edit decal: stripes = bands across --edit-decal-axis; checker = a 3D checker of "
        "cubes; disc = a disc with a ring, on the part's side that --edit-decal-axis points to "
        "(all centred on the centre of the part's bounding box, fixed to the surface)",
        choices=list(DECAL_PATTERNS),
    )
    edit_decal_colors: list[float] = option(
        [1.0, 0.85, 0.1, 0.1, 0.2, 0.8],
        "texture edit decal: its two colours R G B R G B in [0, 1] (the disc's inside, its ring)",
        low=0.0,
        high=1.0,
    )
    edit_decal_size: float = option(
        0.08,
        "texture edit decal: stripe width, checker cube side or disc radius (run units; the "
        "object's bounding sphere has radius 0.8)",
    )
    edit_decal_axis: list[float] | None = option(
        None,
        "texture edit decal: direction X Y Z across the stripes / towards the disc's side; if "
        "omitted, +z for stripes (horizontal bands), +x for the disc (the side facing the first "
        "camera, r_000)",
    )
    edit_hue: float = option(120.0, "texture edit: hue rotation in degrees")
    edit_color: list[float] | None = option(
        None, "texture edit: replace the part's colour by R G B in [0, 1] instead of a hue shift"
    )
    edit_texture: Path | None = option(
        None, "texture edit: replace the mesh's texture image by this image instead"
    )
    cameras_from: Path | None = option(
        None,
        "the folder of an earlier `sine synth` output: render with its cameras (cameras.json) "
        "instead of framing the object anew, e.g. another edit of the same capture",
    )
    supersample: int = option(
        3,
        "rays per pixel side: the colour is the mean of N x N rays over each pixel, as a camera "
        "pixel integrates light (1: one ray through the centre, which aliases fine texture); "
        "odd; masks, depth and labels come from the centre ray",
        low=1,
    )
    format: str = option(
        "sine",
        "output layout: sine (images/, masks/, depth/, labels/, transforms.json, cameras.json) or "
        "nerf-synthetic (all that, plus the Blender/NeRF-synthetic dataset in nerf_synthetic/: "
        "RGBA train/ and test/ images with alpha = mask, transforms_train/val/test.json; val "
        "repeats the test views)",
        choices=list(OUTPUT_FORMATS),
    )

    def __post_init__(self):
        # three numbers stay numbers (a colour), whether they came from the CLI (text) or code
        try:
            if len(self.background) == 3:
                self.background = [float(c) for c in self.background]
        except (TypeError, ValueError):
            pass  # not a colour: parse_background explains


def _validate(cfg: SynthConfig) -> None:
    if (cfg.mesh is None) == (cfg.procedural is None):
        raise SineError("give exactly one of --mesh PATH or --procedural NAME")
    if cfg.views < 3:
        raise SineError(f"--views must be at least 3 (got {cfg.views})")
    if cfg.width < 8 or cfg.height < 8:
        raise SineError("--width and --height must be at least 8 pixels")
    if not 1.0 < cfg.fov < 170.0:
        raise SineError("--fov must be between 1 and 170 degrees")
    if not 0.05 <= cfg.fill <= 1.0:
        raise SineError("--fill must be in [0.05, 1]")
    if cfg.supersample < 1 or cfg.supersample % 2 == 0:
        raise SineError(f"--supersample must be an odd number >= 1 (got {cfg.supersample})")
    parse_background(cfg.background)
    for name in ("parts_plane", "edit_plane"):
        value = getattr(cfg, name)
        if value is not None and len(value) != 4:
            raise SineError(f"--{name.replace('_', '-')} takes four numbers NX NY NZ D")
    if cfg.edit_color is not None and len(cfg.edit_color) != 3:
        raise SineError("--edit-color takes three numbers R G B in [0, 1]")
    if cfg.edit_operation not in GEOMETRIC_OPERATIONS:
        raise SineError(
            f"unknown --edit-operation {cfg.edit_operation!r}; "
            f"use {' or '.join(GEOMETRIC_OPERATIONS)}"
        )
    if cfg.edit_texture_operation not in TEXTURE_OPERATIONS:
        raise SineError(
            f"unknown --edit-texture-operation {cfg.edit_texture_operation!r}; "
            f"use {' or '.join(TEXTURE_OPERATIONS)}"
        )
    if cfg.edit_decal not in DECAL_PATTERNS:
        raise SineError(
            f"unknown --edit-decal {cfg.edit_decal!r}; use one of {', '.join(DECAL_PATTERNS)}"
        )
    if not np.isfinite(cfg.edit_scale) or cfg.edit_scale <= 0:
        raise SineError(f"--edit-scale must be a positive factor (got {cfg.edit_scale})")
    if cfg.edit_pivot is not None and len(cfg.edit_pivot) != 3:
        raise SineError("--edit-pivot takes three numbers X Y Z (run units)")
    colors = cfg.edit_decal_colors
    if len(colors) != 6 or not all(0.0 <= float(c) <= 1.0 for c in colors):
        raise SineError("--edit-decal-colors takes six numbers R G B R G B, each in [0, 1]")
    if not np.isfinite(cfg.edit_decal_size) or cfg.edit_decal_size <= 0:
        raise SineError(f"--edit-decal-size must be positive (got {cfg.edit_decal_size})")
    if cfg.edit_decal_axis is not None and (
        len(cfg.edit_decal_axis) != 3 or np.linalg.norm(cfg.edit_decal_axis) < 1e-12
    ):
        raise SineError("--edit-decal-axis takes three numbers X Y Z, not all zero")
    if cfg.edit_pivot is not None and cfg.edit_operation != "scale_part":
        raise SineError("--edit-pivot is the fixed point of --edit-operation scale_part only")
    if cfg.edit_texture is not None and cfg.edit_texture_operation == "decal":
        raise SineError(
            "--edit-texture replaces the whole texture image: it cannot be combined with "
            "--edit-texture-operation decal (choose one)"
        )
    unknown = [e for e in cfg.edit if e not in EDIT_KINDS]
    if unknown:
        raise SineError(f"unknown edit {unknown[0]!r}; use {' or '.join(EDIT_KINDS)}")
    if cfg.format not in OUTPUT_FORMATS:
        raise SineError(f"unknown --format {cfg.format!r}; use {' or '.join(OUTPUT_FORMATS)}")
    if cfg.edit_texture is not None and not Path(cfg.edit_texture).is_file():
        raise SineError(f"--edit-texture {cfg.edit_texture} does not exist")


def load_source(cfg: SynthConfig) -> tuple[MeshData, Normalisation, dict]:
    """The normalised mesh to render and what the object suggests for edits."""
    hints: dict = {}
    if cfg.procedural is not None:
        obj = procedural.build(cfg.procedural)
        mesh, norm = normalise(obj.mesh, "z")
        if obj.edit_plane is not None:
            hints["edit_plane"] = norm.plane_to_run(obj.edit_plane)
        hints["edit_part"] = obj.edit_part
        hints["up_axis"] = "z"
    else:
        path = Path(cfg.mesh)
        up = resolve_up_axis(cfg.up_axis, path)
        mesh, norm = normalise(load_mesh_file(path), up)
        hints["up_axis"] = up
        if len(mesh.part_names) < 2:
            plane = cfg.parts_plane if cfg.parts_plane is not None else [0.0, 0.0, 1.0, 0.0]
            mesh = mesh.replace(
                part_plane=normalised_plane(plane), part_names={1: "below", 2: "above"}
            )
        hints["edit_part"] = 2 if mesh.part_plane is not None else 1
    return mesh, norm, hints


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
            "elsewhere; see recon.synth.gt_displacement",
            "shared_vertices": "a vertex at the same position as a vertex of the part moves with "
            "the part (the mesh stays connected; the other part's faces at the seam stretch)",
            "membership": "a mesh vertex: it or a vertex at its position is on a face of the part "
            "(with part_plane: on the part's side of the plane, label 2 above, 1 below); any "
            "other point: the part of the nearest GT surface point, ties to the part "
            "(recon.synth.gt_part_membership)",
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
            "formula": "x' = x + (scale - 1) * G(n.x - D) * n, see recon.synth.stretch_displacement",
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
        "(recon.synth.load_gt_edit)",
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


def _view_counts(cameras, views, edit_views, params: dict) -> dict:
    """Per view: the pixels the edit changes (8-bit colour or mask) and, for a part edit, the
    part's pixels in the edited views (a part on one side of the object is not in every view)."""
    changed, part_pixels = {}, {}
    for cam, view, edit_view in zip(cameras, views, edit_views, strict=True):
        stem = Path(cam.name).stem

        def q(rgb):  # as written to the PNGs
            return (np.clip(rgb, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)

        diff = np.any(q(view["rgb"]) != q(edit_view["rgb"]), axis=-1)
        changed[stem] = int((diff | (view["mask"] != edit_view["mask"])).sum())
        if "part" in params:
            part_pixels[stem] = int((edit_view["labels"] == params["part"]).sum())
    out = {"changed_pixels_per_view": changed}
    if part_pixels:
        out["part_pixels_per_view"] = part_pixels
    return out


def reused_cameras(cfg: SynthConfig) -> list[Camera]:
    """The cameras of the `sine synth` output `cfg.cameras_from` (same count and size)."""
    path = Path(cfg.cameras_from) / "cameras.json"
    if not path.is_file():
        raise SineError(f"--cameras-from {cfg.cameras_from}: no cameras.json there")
    cameras = load_cameras(path).frames
    if len(cameras) != cfg.views or any(
        (c.width, c.height) != (cfg.width, cfg.height) for c in cameras
    ):
        raise SineError(
            f"--cameras-from {cfg.cameras_from} has {len(cameras)} views of "
            f"{cameras[0].width}x{cameras[0].height}; give the same --views, --width, --height"
        )
    return cameras


def synthesize(cfg: SynthConfig, progress: bool = True) -> dict:
    """Renders the turntable (and any requested edits) into `cfg.out`; returns a summary."""
    _validate(cfg)
    t0 = time.perf_counter()
    mesh, norm, hints = load_source(cfg)
    edits = _edited_meshes(cfg, mesh, hints)
    t_load = time.perf_counter() - t0

    if cfg.cameras_from is not None:
        cameras = reused_cameras(cfg)
        distance = float(np.mean([np.linalg.norm(c.center) for c in cameras]))
    else:  # one camera set for the original and every edit, framing all of them
        every = np.concatenate([mesh.vertices] + [e[1].vertices for e in edits])
        distance = fit_camera_distance(
            every, cfg.views, cfg.width, cfg.height, cfg.elevation, cfg.fov, cfg.fill
        )
        cameras = ring_cameras(cfg.views, cfg.width, cfg.height, cfg.elevation, distance, cfg.fov)
    background = make_backdrop(cfg.background, cfg.background_seed, distance)
    out = Path(cfg.out)

    t1 = time.perf_counter()
    views = render_views(
        mesh,
        cameras,
        background,
        ambient=cfg.ambient,
        progress=progress,
        supersample=cfg.supersample,
    )
    t_render = time.perf_counter() - t1
    t2 = time.perf_counter()
    stats = write_views(out, cameras, views, mesh)
    if cfg.format == "nerf-synthetic":
        write_nerf_synthetic(out / NERF_SYNTHETIC_DIR, cameras, views)
        stats["nerf_synthetic"] = str(out / NERF_SYNTHETIC_DIR)
    t_write = time.perf_counter() - t2

    summary = {
        "out": str(out),
        "source": str(cfg.mesh) if cfg.mesh is not None else f"procedural:{cfg.procedural}",
        **stats,
        "parts": {str(k): v for k, v in mesh.part_names.items()},
        "camera_distance": distance,
        "seconds_load": t_load,
        "seconds_render": t_render,
        "seconds_write": t_write,
        "edits": {},
    }
    for name, edited, params in edits:
        t3 = time.perf_counter()
        edit_views = render_views(
            edited,
            cameras,
            background,
            ambient=cfg.ambient,
            progress=progress,
            supersample=cfg.supersample,
        )
        edit_dir = out / "edits" / name
        edit_stats = write_views(edit_dir, cameras, edit_views, edited)
        params = {**params, **_view_counts(cameras, views, edit_views, params)}
        if name == "geometric":
            _save_gt_mesh(edit_dir / GT_DISPLACEMENT_FILE, gt_mesh(mesh, edited))
        if cfg.format == "nerf-synthetic":
            write_nerf_synthetic(edit_dir / NERF_SYNTHETIC_DIR, cameras, edit_views)
            edit_stats["nerf_synthetic"] = str(edit_dir / NERF_SYNTHETIC_DIR)
        write_json(edit_dir / "edit.json", params)
        summary["edits"][name] = {**edit_stats, "seconds": time.perf_counter() - t3}

    write_json(
        out / "synth.json",
        {
            "config": to_dict(cfg),
            "up_axis": hints["up_axis"],
            "normalization": norm.to_dict(),
            "object_radius": OBJECT_RADIUS,
            "part_plane": None if mesh.part_plane is None else mesh.part_plane.tolist(),
            "lights": [{"direction": list(d), "intensity": p} for d, p in DEFAULT_LIGHTS],
            "ambient": cfg.ambient,
            "summary": summary,
        },
    )
    summary["seconds_total"] = time.perf_counter() - t0
    return summary
