"""Built-in procedural objects for synthetic turntables: no outside data needed.

Each object is a union of trimesh primitives (overlaps are fine for ray casting) with named parts
and a procedural texture computed from the 3D position (stripes, checkers, windows, hubcaps), so
it has the detail that feature matching and radiance fields need. Coordinates are z-up, in the
object's own units; `recon.synth.normalise` brings them to run units.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from recon.mesh_data import MeshData
from render.errors import SineError


@dataclass
class ProceduralObject:
    mesh: MeshData
    edit_plane: np.ndarray | None  # suggested geometric-edit plane (n, D), object units
    edit_part: int  # suggested part to recolour


def _assemble(pieces: list[tuple], part_names: dict[int, str], color_fn) -> MeshData:
    """pieces: (trimesh.Trimesh, part id, smooth shading?) -> one MeshData."""
    verts, faces, parts, smooth = [], [], [], []
    offset = 0
    for mesh, part, is_smooth in pieces:
        verts.append(np.asarray(mesh.vertices, dtype=np.float64))
        faces.append(np.asarray(mesh.faces, dtype=np.int64) + offset)
        parts.append(np.full(len(mesh.faces), part, dtype=np.int64))
        smooth.append(np.full(len(mesh.faces), is_smooth, dtype=bool))
        offset += len(mesh.vertices)
    face_parts = np.concatenate(parts)

    def albedo(points, face_ids):  # [N, 3], [N] -> [N, 3]
        return color_fn(np.asarray(points, np.float64), face_parts[np.asarray(face_ids)])

    return MeshData(
        vertices=np.concatenate(verts),
        faces=np.concatenate(faces),
        part_names=part_names,
        face_parts=face_parts,
        face_smooth=np.concatenate(smooth),
        color_fn=albedo,
    )


def _checker(a: np.ndarray, b: np.ndarray, cell: float) -> np.ndarray:
    return (np.floor(a / cell) + np.floor(b / cell)).astype(np.int64) % 2 == 1


def _mix(mask: np.ndarray, color_true, color_false) -> np.ndarray:
    return np.where(mask[:, None], np.asarray(color_true), np.asarray(color_false))


# ---- toy car ------------------------------------------------------------------------------
BODY = dict(center=(0.0, 0.0, 0.425), extents=(2.0, 0.9, 0.45))
CABIN = dict(center=(-0.15, 0.0, 0.83), extents=(1.0, 0.8, 0.42))
WHEEL_RADIUS, WHEEL_WIDTH, WHEEL_X, WHEEL_Y, WHEEL_Z = 0.25, 0.18, 0.62, 0.43, 0.25


def _toycar_colors(p: np.ndarray, part: np.ndarray) -> np.ndarray:
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    out = np.zeros((len(p), 3))
    red, white, black = (0.82, 0.12, 0.1), (0.95, 0.95, 0.92), (0.08, 0.08, 0.1)

    # Body: red, two white racing stripes along x, a checker band low on the sides,
    # yellow headlights in front, dark-red tail lights at the back.
    body = part == 1
    c = _mix(((np.abs(y) > 0.07) & (np.abs(y) < 0.17)) & (z > 0.6), white, red)
    band = (z < 0.36) & (np.abs(y) > 0.4)
    c = np.where(band[:, None], _mix(_checker(x + 2, z, 0.08), black, white), c)
    front, back = x > 0.97, x < -0.97
    lamp = (np.abs(np.abs(y) - 0.3) < 0.08) & (np.abs(z - 0.52) < 0.05)
    c = np.where((front & lamp)[:, None], np.array([1.0, 0.85, 0.2]), c)
    c = np.where((back & lamp)[:, None], np.array([0.45, 0.02, 0.02]), c)
    grille = front & (np.abs(y) < 0.18) & (np.abs(z - 0.42) < 0.08)
    c = np.where(grille[:, None], _mix(np.floor(z / 0.03) % 2 == 0, black, (0.6, 0.6, 0.6)), c)
    out[body] = c[body]

    # Cabin: cream roof with a small checker, dark glass windows with pillars.
    cabin = part == 2
    cx = x - CABIN["center"][0]
    roof = _mix(_checker(x + 2, y + 2, 0.1), (0.95, 0.88, 0.7), (0.85, 0.75, 0.55))
    glass_band = (z > 0.7) & (z < 0.99)
    side_glass = (np.abs(y) > 0.38) & (np.abs(cx) < 0.42) & (np.abs(cx + 0.02) > 0.04)
    end_glass = (np.abs(cx) > 0.48) & (np.abs(y) < 0.32)
    glass = glass_band & (side_glass | end_glass)
    c = _mix(glass, (0.15, 0.25, 0.4), roof)
    out[cabin] = c[cabin]

    # Wheels: dark tyres with tread marks, light hubcaps with five spokes.
    wheel = part == 3
    wx = x - np.sign(x) * WHEEL_X
    wz = z - WHEEL_Z
    r = np.hypot(wx, wz)
    angle = np.arctan2(wz, wx)
    tread = (np.floor(angle / (2 * np.pi) * 24) % 2 == 0) & (r > WHEEL_RADIUS - 0.02)
    c = _mix(tread, (0.16, 0.16, 0.16), (0.06, 0.06, 0.06))
    spokes = np.cos(5 * angle) > 0.3
    hub = r < 0.13
    c = np.where(hub[:, None], _mix(spokes | (r < 0.04), (0.8, 0.8, 0.82), (0.35, 0.35, 0.4)), c)
    out[wheel] = c[wheel]
    return out


def toycar() -> ProceduralObject:
    """A toy car: box body, box cabin, four cylinder wheels (parts: body, cabin, wheels)."""
    import trimesh

    body = trimesh.creation.box(
        extents=BODY["extents"],
        transform=trimesh.transformations.translation_matrix(BODY["center"]),
    )
    cabin = trimesh.creation.box(
        extents=CABIN["extents"],
        transform=trimesh.transformations.translation_matrix(CABIN["center"]),
    )
    pieces = [(body, 1, False), (cabin, 2, False)]
    axis_y = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])
    for sx in (-1, 1):
        for sy in (-1, 1):
            move = trimesh.transformations.translation_matrix((sx * WHEEL_X, sy * WHEEL_Y, WHEEL_Z))
            wheel = trimesh.creation.cylinder(
                radius=WHEEL_RADIUS, height=WHEEL_WIDTH, sections=48, transform=move @ axis_y
            )
            pieces.append((wheel, 3, False))
    mesh = _assemble(pieces, {1: "body", 2: "cabin", 3: "wheels"}, _toycar_colors)
    top_of_body = BODY["center"][2] + BODY["extents"][2] / 2
    # Suggested edit: stretch the cabin upwards (plane just above the body's top).
    return ProceduralObject(mesh, np.array([0.0, 0.0, 1.0, top_of_body + 0.02]), edit_part=1)


# ---- figurine -----------------------------------------------------------------------------
def _figurine_colors(p: np.ndarray, part: np.ndarray) -> np.ndarray:
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    out = np.zeros((len(p), 3))
    angle = np.arctan2(y, x)
    # Base: wood-like rings with a checker rim.
    base = part == 1
    ring = np.floor(np.hypot(x, y) / 0.06) % 2 == 0
    c = _mix(ring, (0.55, 0.36, 0.2), (0.45, 0.28, 0.15))
    rim = z < 0.12
    c = np.where(
        rim[:, None], _mix(_checker(angle * 3, z, 0.04), (0.1, 0.1, 0.1), (0.9, 0.85, 0.6)), c
    )
    out[base] = c[base]
    # Body: blue with white horizontal stripes and coloured buttons in front.
    body = part == 2
    c = _mix(np.floor(z / 0.07) % 2 == 0, (0.15, 0.3, 0.75), (0.92, 0.92, 0.95))
    buttons = (x > 0.2) & (np.abs(y) < 0.06) & (np.abs(((z - 0.3) % 0.15) - 0.075) < 0.04)
    c = np.where(buttons[:, None], np.array([0.95, 0.75, 0.1]), c)
    out[body] = c[body]
    # Head: skin tone, two eyes and a mouth facing +x.
    head = part == 3
    hz = z - 1.1
    eyes = (x > 0.12) & (np.abs(np.abs(y) - 0.08) < 0.035) & (np.abs(hz - 0.05) < 0.035)
    mouth = (x > 0.15) & (np.abs(y) < 0.08) & (np.abs(hz + 0.07) < 0.018)
    c = np.full((len(p), 3), (0.96, 0.8, 0.66))
    c = np.where((eyes | mouth)[:, None], np.array([0.1, 0.05, 0.05]), c)
    out[head] = c[head]
    # Hat: red cone with a yellow zig-zag band.
    hat = part == 4
    zig = np.abs(z - 1.36 - 0.03 * np.sin(8 * angle)) < 0.025
    c = _mix(zig, (0.98, 0.85, 0.15), (0.8, 0.1, 0.15))
    out[hat] = c[hat]
    return out


def figurine() -> ProceduralObject:
    """A little figurine: base, body, head, hat (parts in that order)."""
    import trimesh

    tr = trimesh.transformations.translation_matrix
    base = trimesh.creation.cylinder(
        radius=0.5, height=0.15, sections=64, transform=tr((0, 0, 0.075))
    )
    body = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    body.apply_transform(tr((0, 0, 0.58)) @ np.diag([0.36, 0.36, 0.46, 1.0]))
    head = trimesh.creation.icosphere(subdivisions=4, radius=0.22)
    head.apply_transform(tr((0, 0, 1.1)))
    hat = trimesh.creation.cone(radius=0.2, height=0.35, sections=48, transform=tr((0, 0, 1.26)))
    pieces = [(base, 1, False), (body, 2, True), (head, 3, True), (hat, 4, False)]
    mesh = _assemble(pieces, {1: "base", 2: "body", 3: "head", 4: "hat"}, _figurine_colors)
    # Suggested edit: stretch head and hat upwards (plane at the neck).
    return ProceduralObject(mesh, np.array([0.0, 0.0, 1.0, 0.98]), edit_part=2)


PROCEDURAL: dict[str, Callable[[], ProceduralObject]] = {"toycar": toycar, "figurine": figurine}


def build(name: str) -> ProceduralObject:
    """The procedural object called `name` (see PROCEDURAL)."""
    if name not in PROCEDURAL:
        raise SineError(f"unknown procedural object {name!r}; choose from {', '.join(PROCEDURAL)}")
    return PROCEDURAL[name]()
