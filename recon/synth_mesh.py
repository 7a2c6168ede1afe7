"""Source meshes of `sine synth` (recon.synth): reading a mesh file into MeshData, normalising it
to run units (centred, bounding-sphere radius OBJECT_RADIUS, up = +z) and planes (n, D).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon.mesh_data import MeshData
from render.errors import SineError

OBJECT_RADIUS = 0.8  # bounding-sphere radius of the normalised mesh, run units
UP_AXES = ("auto", "z", "y", "x", "-z", "-y", "-x")


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
