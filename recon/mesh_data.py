"""A triangle mesh with what a renderer needs to colour and label a hit (`MeshData`), and the
lookups it uses: plane sides, bilinear texture sampling, the recolouring of a texture edit.

Shared by `recon.synth` (which loads, normalises, edits and renders it) and `recon.procedural`
(which builds one); neither imports the other for it.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from dataclasses import dataclass, field

import cv2
import numpy as np

ColorFn = Callable[[np.ndarray, np.ndarray], np.ndarray]  # (rest points [N,3], faces [N]) -> [N,3]


@dataclass
class MeshData:
    """A triangle mesh with everything the renderer needs to colour and label a hit.

    `vertices` are the positions rendered; `rest_vertices` the positions before any geometric
    edit: colour (procedural textures) and the plane split of parts are looked up there, so they
    move with the geometry.
    """

    vertices: np.ndarray  # [V, 3] float64
    faces: np.ndarray  # [F, 3] int64
    part_names: dict[int, str]  # part id -> name (0 = background, never a part)
    face_parts: np.ndarray  # [F] int part ids (used when part_plane is None)
    vertex_colors: np.ndarray | None = None  # [V, 3] float32 albedo where no texture/color_fn
    face_uvs: np.ndarray | None = None  # [F, 3, 2] texture coordinates per face corner
    face_texture: np.ndarray | None = None  # [F] index into `textures`, -1 = vertex colours
    textures: list[np.ndarray] = field(default_factory=list)  # float32 RGB [H, W, 3]
    color_fn: ColorFn | None = None  # procedural albedo, evaluated at rest positions
    face_smooth: np.ndarray | None = None  # [F] bool: interpolate vertex normals (else flat)
    part_plane: np.ndarray | None = None  # [4] (n, D): label 1 below, 2 above (rest positions)
    rest_vertices: np.ndarray | None = None  # [V, 3]; None = `vertices`
    weld: np.ndarray | None = None  # [V] index of the vertex after merging equal positions
    recolor: dict | None = None  # texture edit of one part: {part, hue_shift_deg, color} or
    # {part, decal: {pattern, colors, size, center, axis}} (see recolor_albedo)

    def __post_init__(self):
        self.vertices = np.asarray(self.vertices, dtype=np.float64).reshape(-1, 3)
        self.faces = np.asarray(self.faces, dtype=np.int64).reshape(-1, 3)
        self.face_parts = np.asarray(self.face_parts, dtype=np.int64).reshape(-1)
        if self.rest_vertices is None:
            self.rest_vertices = self.vertices.copy()
        if self.weld is None:
            _, self.weld = np.unique(self.vertices, axis=0, return_inverse=True)
            self.weld = self.weld.reshape(-1)
        if self.face_smooth is None:
            self.face_smooth = np.ones(len(self.faces), dtype=bool)
        if self.face_texture is None:
            self.face_texture = np.full(len(self.faces), -1, dtype=np.int64)
        if self.vertex_colors is None:
            self.vertex_colors = np.full((len(self.vertices), 3), 0.7, dtype=np.float32)

    def replace(self, **changes) -> MeshData:
        return dataclasses.replace(self, **changes)

    def subdivided(self, max_edge: float, where: Callable[[np.ndarray], np.ndarray]) -> MeshData:
        """The same surface with every face that `where(vertices [V, 3]) -> [V] bool` selects
        (any of its corners) split at its edges' midpoints until no selected face has an edge
        longer than `max_edge`: a displacement applied at the vertices then follows a smooth
        field inside big faces too. The original vertices keep their indices (new ones are
        appended); every per-face and per-vertex attribute is carried over (per-vertex ones and
        UVs by their barycentric coordinates in the face they split)."""
        import trimesh

        vertices, faces = self.vertices, self.faces
        rest, colours = self.rest_vertices, self.vertex_colors
        origin = np.arange(len(faces))  # [F'] the original face of each face
        for _ in range(12):
            tri = vertices[faces]
            longest = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2).max(axis=1)
            split = np.flatnonzero((longest > max_edge) & where(vertices)[faces].any(axis=1))
            if len(split) == 0:
                break
            new_vertices, new_faces, children = trimesh.remesh.subdivide(
                vertices, faces, face_index=split, return_index=True
            )
            parent = np.empty(len(new_faces), np.int64)  # the face each new face split from
            keep = np.setdiff1d(np.arange(len(faces)), split)
            parent[: len(keep)] = keep
            for face, kids in children.items():
                parent[kids] = face
            # the appended vertices' attributes, by their barycentrics in the face they split
            corner_ids = new_faces.reshape(-1)
            added = corner_ids >= len(vertices)
            ids, parents = corner_ids[added], np.repeat(parent, 3)[added]
            bary = _barycentric(vertices[faces[parents]], new_vertices[ids][:, None])[:, 0]
            rest_new = np.empty((len(new_vertices), 3))
            colours_new = np.empty((len(new_vertices), 3), np.float32)
            rest_new[: len(vertices)], colours_new[: len(vertices)] = rest, colours
            rest_new[ids] = np.einsum("nk,nkd->nd", bary, rest[faces[parents]])
            colours_new[ids] = np.einsum("nk,nkd->nd", bary, colours[faces[parents]])
            vertices, faces, rest, colours = new_vertices, new_faces, rest_new, colours_new
            origin = origin[parent]
        if len(faces) == len(self.faces):
            return self
        uvs = None
        if self.face_uvs is not None:  # each new corner's barycentrics in its original face
            bary = _barycentric(self.rest_vertices[self.faces[origin]], rest[faces])  # [F, 3, 3]
            uvs = np.einsum("fkc,fcu->fku", bary, self.face_uvs[origin])
        color_fn = self.color_fn
        if color_fn is not None:  # a procedural albedo reads the original faces' ids

            def color_fn(points, face_ids, source=self.color_fn, origin=origin):
                return source(points, origin[np.asarray(face_ids)])

        return self.replace(
            vertices=vertices,
            faces=faces,
            color_fn=color_fn,
            rest_vertices=rest,
            vertex_colors=colours,
            face_parts=self.face_parts[origin],
            face_uvs=uvs,
            face_texture=self.face_texture[origin],
            face_smooth=self.face_smooth[origin],
            weld=_appended_weld(self.weld, vertices[len(self.vertices) :]),
        )

    # ---- per-hit lookups ------------------------------------------------------------------
    def rest_points(self, face_ids: np.ndarray, bary: np.ndarray) -> np.ndarray:
        """Rest-space positions [N, 3] of hits given by faces [N] and barycentrics [N, 3]."""
        return np.einsum("nk,nkd->nd", bary, self.rest_vertices[self.faces[face_ids]])

    def labels_at(self, face_ids: np.ndarray, rest_points: np.ndarray) -> np.ndarray:
        """Part id [N] of hits."""
        if self.part_plane is not None:
            return np.where(plane_side(rest_points, self.part_plane) > 0, 2, 1).astype(np.int64)
        return self.face_parts[face_ids]

    def albedo_at(self, face_ids: np.ndarray, bary: np.ndarray, rest_points: np.ndarray):
        """Surface colour [N, 3] (float32, before shading) of hits, texture edit included."""
        if self.color_fn is not None:
            albedo = np.asarray(self.color_fn(rest_points, face_ids), dtype=np.float32)
        else:
            corner = self.vertex_colors[self.faces[face_ids]]  # [N, 3, 3]
            albedo = np.einsum("nk,nkd->nd", bary, corner).astype(np.float32)
            tex_ids = self.face_texture[face_ids]
            for t, image in enumerate(self.textures):
                sel = tex_ids == t
                if sel.any():
                    uv = np.einsum("nk,nkd->nd", bary[sel], self.face_uvs[face_ids[sel]])
                    albedo[sel] = sample_texture(image, uv)
        return self._recolored(albedo, self.labels_at(face_ids, rest_points), rest_points)

    # ---- per-vertex values (the exported GT mesh) -----------------------------------------
    def vertex_faces(self) -> np.ndarray:
        """One incident face per vertex [V] (0 for unused vertices)."""
        out = np.zeros(len(self.vertices), dtype=np.int64)
        out[self.faces.ravel()] = np.repeat(np.arange(len(self.faces)), 3)
        return out

    def vertex_labels(self) -> np.ndarray:
        """Part id per vertex [V] (rest positions for the plane split)."""
        return self.labels_at(self.vertex_faces(), self.rest_vertices)

    def vertex_albedo(self) -> np.ndarray:
        """Albedo per vertex [V, 3] float32: texture sampled at the vertex's UV, texture edit in."""
        vf = self.vertex_faces()
        if self.color_fn is not None:
            albedo = np.asarray(self.color_fn(self.rest_vertices, vf), dtype=np.float32)
        else:
            albedo = self.vertex_colors.astype(np.float32).copy()
            for t, image in enumerate(self.textures):
                sel = self.face_texture == t
                if sel.any():
                    corner_uv = self.face_uvs[sel].reshape(-1, 2)
                    albedo[self.faces[sel].ravel()] = sample_texture(image, corner_uv)
        return self._recolored(albedo, self.vertex_labels(), self.rest_vertices)

    def _recolored(self, albedo: np.ndarray, labels: np.ndarray, rest_points: np.ndarray):
        if not self.recolor:
            return albedo
        sel = labels == int(self.recolor["part"])
        if sel.any():
            albedo = albedo.copy()
            albedo[sel] = recolor_albedo(albedo[sel], self.recolor, rest_points[sel])
        return albedo

    # ---- geometry -------------------------------------------------------------------------
    def welded(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Vertices merged by position: (vertices [W, 3], faces [F, 3], first original index [W])."""
        n = int(self.weld.max()) + 1 if len(self.weld) else 0
        first = np.full(n, -1, dtype=np.int64)
        first[self.weld[::-1]] = np.arange(len(self.weld))[::-1]
        return self.vertices[first], self.weld[self.faces], first

    def normals(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit face normals [F, 3] and smooth vertex normals [V, 3] (area weighted, welded)."""
        tri = self.vertices[self.faces]
        cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])  # [F, 3], |.| = 2 area
        face_n = cross / np.maximum(np.linalg.norm(cross, axis=1, keepdims=True), 1e-20)
        wv, wf, _ = self.welded()
        acc = np.zeros_like(wv)
        for k in range(3):
            np.add.at(acc, wf[:, k], cross)
        acc /= np.maximum(np.linalg.norm(acc, axis=1, keepdims=True), 1e-20)
        return face_n, acc[self.weld]

    def to_trimesh(self):
        """The welded mesh with per-vertex albedo colours (uint8), ready for PLY export."""
        import trimesh

        wv, wf, first = self.welded()
        colors = self.vertex_albedo()[first]
        rgba = np.concatenate([colors, np.ones((len(colors), 1), np.float32)], axis=1)
        return trimesh.Trimesh(
            wv, wf, vertex_colors=(np.clip(rgba, 0, 1) * 255 + 0.5).astype(np.uint8), process=False
        )

    def welded_vertex_labels(self) -> np.ndarray:
        return self.vertex_labels()[self.welded()[2]]


def plane_side(points: np.ndarray, plane) -> np.ndarray:
    """Signed distance [N] of points [N, 3] to the plane (n, D) (n normalised here)."""
    plane = np.asarray(plane, dtype=np.float64).reshape(4)
    n = plane[:3] / np.linalg.norm(plane[:3])
    return np.asarray(points, dtype=np.float64) @ n - plane[3]


def sample_texture(image: np.ndarray, uv: np.ndarray) -> np.ndarray:
    """Bilinear lookup [N, 3] of texture [H, W, 3] at UVs [N, 2] (v up, repeat wrapping)."""
    h, w = image.shape[:2]
    x = np.asarray(uv[:, 0], dtype=np.float64) * w - 0.5
    y = (1.0 - np.asarray(uv[:, 1], dtype=np.float64)) * h - 0.5
    x0, y0 = np.floor(x), np.floor(y)
    fx, fy = (x - x0)[:, None].astype(np.float32), (y - y0)[:, None].astype(np.float32)
    x0, y0 = x0.astype(np.int64), y0.astype(np.int64)
    x1, y1 = (x0 + 1) % w, (y0 + 1) % h
    x0, y0 = x0 % w, y0 % h
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return (top * (1 - fy) + bottom * fy).astype(np.float32)


def decal_pattern(points: np.ndarray, decal: dict) -> tuple[np.ndarray, np.ndarray]:
    """Where a decal paints the rest-space points [N, 3], and with which of its two colours:
    (painted [N] bool, colour index [N] 0 or 1). A function of the 3D point alone, so the same
    surface point has the same colour in every view, and the decal moves with a geometric edit.

    With q = (p - center) / size and a = axis (unit):
    - stripes: bands of width `size` across `axis`: colour floor(q.a + 1/2) mod 2 (colour 0 on
      the band through the centre), everywhere;
    - checker: cubes of side `size`: colour (sum of floor(q + 1/2)) mod 2, everywhere (on a flat
      face, a checkerboard);
    - disc: a roundel projected along `axis` onto the side it points to (q.a > 0): colour 0
      within distance 1 (one `size`) of the axis line, colour 1 in the ring from 1 to 1.5; the
      rest keeps its colour.
    """
    q = (np.asarray(points, np.float64) - np.asarray(decal["center"], np.float64)) / float(
        decal["size"]
    )
    pattern = decal["pattern"]
    if pattern == "checker":
        index = np.floor(q + 0.5).astype(np.int64).sum(axis=1) % 2
        return np.ones(len(q), dtype=bool), index
    axis = np.asarray(decal["axis"], np.float64)
    axis = axis / np.linalg.norm(axis)
    along = q @ axis
    if pattern == "stripes":
        return np.ones(len(q), dtype=bool), np.floor(along + 0.5).astype(np.int64) % 2
    if pattern == "disc":
        radial = np.linalg.norm(q - along[:, None] * axis, axis=1)
        painted = (along > 0) & (radial < 1.5)
        return painted, (radial >= 1.0).astype(np.int64)
    raise ValueError(f"unknown decal pattern {pattern!r}")


def recolor_albedo(albedo: np.ndarray, recolor: dict, points: np.ndarray | None = None):
    """Texture edit of colours [N, 3] at rest points [N, 3]: a `decal` (`decal_pattern`; needs
    the points), else a solid `color`, else a hue rotation by `hue_shift_deg`."""
    if recolor.get("decal") is not None:
        if points is None:
            raise ValueError("a decal needs the surface points")
        painted, index = decal_pattern(points, recolor["decal"])
        colors = np.asarray(recolor["decal"]["colors"], np.float32).reshape(2, 3)
        out = np.array(albedo, dtype=np.float32, copy=True)
        out[painted] = colors[index[painted]]
        return out
    if recolor.get("color") is not None:
        return np.broadcast_to(np.asarray(recolor["color"], np.float32), albedo.shape).copy()
    hsv = cv2.cvtColor(np.clip(albedo, 0, 1).astype(np.float32)[None], cv2.COLOR_RGB2HSV)[0]
    hsv[:, 0] = (hsv[:, 0] + float(recolor.get("hue_shift_deg", 0.0))) % 360.0
    # Grey surfaces have no hue to rotate: give them some saturation so the edit is visible.
    hsv[:, 1] = np.maximum(hsv[:, 1], float(recolor.get("min_saturation", 0.0)))
    return cv2.cvtColor(hsv[None], cv2.COLOR_HSV2RGB)[0]


def _barycentric(triangles: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Barycentric coordinates [F, K, 3] of points [F, K, 3] in triangles [F, 3, 3]."""
    a, b, c = triangles[:, 0:1], triangles[:, 1:2], triangles[:, 2:3]  # [F, 1, 3]
    v0, v1, v2 = b - a, c - a, points - a
    d00, d01, d11 = (v0 * v0).sum(-1), (v0 * v1).sum(-1), (v1 * v1).sum(-1)
    d20, d21 = (v2 * v0).sum(-1), (v2 * v1).sum(-1)
    denom = np.maximum(d00 * d11 - d01 * d01, 1e-30)
    v = (d11 * d20 - d01 * d21) / denom
    w = (d00 * d21 - d01 * d20) / denom
    return np.stack([1.0 - v - w, v, w], axis=-1)


def _appended_weld(weld: np.ndarray, added: np.ndarray) -> np.ndarray:
    """The weld [V + A] of a mesh whose vertices `added` [A, 3] were appended: the old vertices
    keep their welded ids (so the welded mesh starts with the old one, in its order), the added
    ones are merged by position after them."""
    _, inverse = np.unique(added, axis=0, return_inverse=True)
    start = int(weld.max()) + 1 if len(weld) else 0
    return np.concatenate([weld, start + inverse.reshape(-1)])
