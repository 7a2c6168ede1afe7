"""Built-in procedural objects for synthetic turntables: no outside data needed.

Each object is a union of trimesh primitives (overlaps are fine for ray casting) with named parts
and a procedural texture computed from the 3D position (stripes, checkers, windows, hubcaps), so
it has the detail that feature matching and radiance fields need. Coordinates are z-up, in the
object's own units; `recon.synth_mesh.normalise` brings them to run units.
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


# ---- mug ----------------------------------------------------------------------------------
MUG_RADIUS, MUG_HEIGHT, MUG_WALL = 0.42, 1.0, 0.045  # outer radius, height, wall thickness
MUG_FLOOR = 0.07  # top of the inner floor
MUG_BAND = dict(z0=0.05, z1=0.15, proud=0.012)  # raised band around the foot
# Handle: a half torus in the x-z plane on the +x side only; its arc's centre sits in the wall
# (x = MUG_RADIUS - HANDLE_INSET) so that both capped ends end inside the wall.
HANDLE_MAJOR, HANDLE_MINOR, HANDLE_Z, HANDLE_INSET = 0.25, 0.05, 0.5, 0.02


def _torus_arc(major: float, minor: float, span_deg: float, sections: int = 48):
    """A closed torus segment: a circle of radius `minor` at distance `major` from the z axis,
    swept `span_deg` degrees about z, centred on +x, its two ends capped by triangle fans
    (trimesh's own caps need shapely)."""
    import trimesh

    t = np.linspace(0.0, 2.0 * np.pi, 25)
    profile = np.stack([major + minor * np.cos(t), minor * np.sin(t)], axis=1)  # (radius, z)
    span = np.radians(span_deg)
    arc = trimesh.creation.revolve(profile, angle=span, sections=sections)
    arc.merge_vertices()
    verts, faces = [np.asarray(arc.vertices)], [np.asarray(arc.faces)]
    n = len(arc.vertices)
    for end in arc.outline().entities:  # the two open end circles
        loop = np.asarray(end.points)[:-1]  # closed: the last point repeats the first
        verts.append(np.asarray(arc.vertices)[loop].mean(axis=0, keepdims=True))
        faces.append(np.stack([np.full(len(loop), n), loop, np.roll(loop, -1)], axis=1))
        n += 1
    closed = trimesh.Trimesh(np.concatenate(verts), np.concatenate(faces), process=True)
    trimesh.repair.fix_normals(closed)  # the caps' winding follows the tube's (outwards)
    closed.apply_transform(trimesh.transformations.rotation_matrix(-span / 2, [0, 0, 1]))
    return closed


def _mug_colors(p: np.ndarray, part: np.ndarray) -> np.ndarray:
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    out = np.zeros((len(p), 3))
    r = np.hypot(x, y)
    angle = np.arctan2(y, x)
    arc_len = angle * MUG_RADIUS  # distance around the outside

    # Body: blue gradient (light at the foot, deep at the rim) with staggered white polka dots, a
    # yellow star opposite the handle (-x) so the body's views differ; cream inside with a coffee
    # ring, a white lip on top of the wall.
    body = part == 1
    t = np.clip(z / MUG_HEIGHT, 0.0, 1.0)[:, None]
    c = (1 - t) * np.array([0.45, 0.7, 0.9]) + t * np.array([0.1, 0.22, 0.6])
    row = np.floor(z / 0.12)
    du = (arc_len + 0.06 * (row % 2)) % 0.12 - 0.06
    dv = z % 0.12 - 0.06
    c = np.where((np.hypot(du, dv) < 0.028)[:, None], np.array([0.97, 0.97, 0.95]), c)
    sx, sz = (np.mod(angle, 2 * np.pi) - np.pi) * MUG_RADIUS, z - 0.55  # centre (-R, 0, 0.55)
    phi = np.arctan2(sz, sx)
    star = np.hypot(sx, sz) < 0.13 * (0.65 + 0.35 * np.cos(5 * (phi - np.pi / 2)))
    c = np.where(star[:, None], np.array([0.98, 0.8, 0.1]), c)
    inside = r < MUG_RADIUS - 0.5 * MUG_WALL
    cream = _mix(np.abs(z - 0.85) < 0.015, (0.55, 0.38, 0.25), (0.95, 0.92, 0.84))
    c = np.where(inside[:, None], cream, c)
    c = np.where((z > MUG_HEIGHT - 1e-3)[:, None], np.array([0.97, 0.97, 0.97]), c)
    out[body] = c[body]

    # Handle: red-orange, darker towards its ends, with a cream stripe along its outer edge.
    handle = part == 2
    hx, hz = x - (MUG_RADIUS - HANDLE_INSET), z - HANDLE_Z
    along = np.abs(np.arctan2(hz, hx)) / (np.pi / 2)  # 0 at the middle, 1 at the ends
    c = (1 - 0.45 * along[:, None]) * np.array([0.9, 0.3, 0.08])
    outer_edge = (np.abs(y) < 0.015) & (np.hypot(hx, hz) > HANDLE_MAJOR)
    c = np.where(outer_edge[:, None], np.array([0.95, 0.9, 0.75]), c)
    out[handle] = c[handle]

    # Band: a navy and yellow checker.
    band = part == 3
    c = _mix(_checker(arc_len + 4.0, z, 0.05), (0.1, 0.1, 0.35), (0.95, 0.8, 0.2))
    out[band] = c[band]
    return out


def mug() -> ProceduralObject:
    """A mug, asymmetric: open body with an inner wall and floor, a handle on the +x side only,
    a raised band around the foot (parts: body, handle, band)."""
    import trimesh

    tr = trimesh.transformations.translation_matrix
    inner = MUG_RADIUS - MUG_WALL
    wall = trimesh.creation.annulus(
        inner, MUG_RADIUS, MUG_HEIGHT, sections=96, transform=tr((0, 0, MUG_HEIGHT / 2))
    )
    floor = trimesh.creation.cylinder(  # reaches into the wall: no gap at the seam
        radius=inner + 0.01, height=MUG_FLOOR, sections=96, transform=tr((0, 0, MUG_FLOOR / 2))
    )
    b = MUG_BAND
    band = trimesh.creation.annulus(
        MUG_RADIUS - 0.01,
        MUG_RADIUS + b["proud"],
        b["z1"] - b["z0"],
        sections=96,
        transform=tr((0, 0, (b["z0"] + b["z1"]) / 2)),
    )
    handle = _torus_arc(HANDLE_MAJOR, HANDLE_MINOR, 180.0)
    upright = trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0])  # arc in x-z
    handle.apply_transform(tr((MUG_RADIUS - HANDLE_INSET, 0, HANDLE_Z)) @ upright)
    pieces = [(wall, 1, False), (floor, 1, False), (handle, 2, True), (band, 3, False)]
    mesh = _assemble(pieces, {1: "body", 2: "handle", 3: "band"}, _mug_colors)
    # Suggested edit: stretch the upper body (rim and the handle's top half) upwards.
    return ProceduralObject(mesh, np.array([0.0, 0.0, 1.0, 0.6 * MUG_HEIGHT]), edit_part=2)


# ---- chair --------------------------------------------------------------------------------
SEAT = dict(half=0.45, z0=0.92, z1=1.0)  # square seat, its bottom and top
LEG_WIDTH, LEG_INSET = 0.09, 0.07  # square legs; leg centres at +-(SEAT half - LEG_INSET)
BACK_TOP = 1.85  # top of the back posts (the chair's height); the back is on the -x side
BACK_RAILS = dict(top=(1.70, 1.85), low=(1.17, 1.23))  # z ranges of the rails between the posts
RAIL_DEPTH = 0.06
SLAT_Y, SLAT_WIDTH, SLAT_DEPTH = (-0.17, 0.0, 0.17), 0.07, 0.04


def _chair_colors(p: np.ndarray, part: np.ndarray) -> np.ndarray:
    x, y, z = p[:, 0], p[:, 1], p[:, 2]
    out = np.zeros((len(p), 3))
    honey, dark_grain = np.array([0.85, 0.6, 0.3]), np.array([0.62, 0.38, 0.16])

    # Seat: five planks along x with dark gaps, wavy grain, each plank a slightly different tint.
    seat = part == 1
    plank = np.floor((y + SEAT["half"]) / (2 * SEAT["half"] / 5))
    grain = 0.5 + 0.5 * np.sin(60 * y + 2.5 * np.sin(5 * x + plank) + 3 * plank)
    c = honey + (dark_grain - honey) * (0.6 * grain**3)[:, None]
    c = c * (0.9 + 0.05 * (plank % 3))[:, None]
    gap = np.abs(((y + SEAT["half"]) % (2 * SEAT["half"] / 5)) - SEAT["half"] / 5) > 0.085
    c = np.where((gap & (z > SEAT["z1"] - 1e-3))[:, None], np.array([0.25, 0.14, 0.06]), c)
    out[seat] = c[seat]

    # Legs: dark green paint with thin light rings, brass feet.
    legs = part == 2
    c = _mix(np.abs(z % 0.22 - 0.11) < 0.012, (0.75, 0.85, 0.7), (0.08, 0.3, 0.2))
    c = np.where((z < 0.06)[:, None], np.array([0.85, 0.7, 0.3]), c)
    out[legs] = c[legs]

    # Back: white-washed frame with vertical grain; red slats with a checker on the top rail.
    back = part == 3
    streak = 0.5 + 0.5 * np.sin(45 * (x + y) + 3 * np.sin(4 * z))
    c = np.array([0.92, 0.9, 0.85]) - 0.12 * streak[:, None]
    between_posts = np.abs(y) < SEAT["half"] - LEG_INSET - LEG_WIDTH / 2 - 1e-3
    slat = between_posts & (z > BACK_RAILS["low"][1] + 1e-3) & (z < BACK_RAILS["top"][0])
    c = np.where(slat[:, None], _mix(streak > 0.8, (0.6, 0.08, 0.1), (0.8, 0.15, 0.15)), c)
    top_rail = between_posts & (z > BACK_RAILS["top"][0] + 1e-3)
    c = np.where(top_rail[:, None], _mix(_checker(y + 2, z, 0.05), (0.1, 0.1, 0.1), c), c)
    out[back] = c[back]
    return out


def chair() -> ProceduralObject:
    """A chair with thin parts: a plank seat, four thin square legs, a back of two posts, two
    rails and three slats on the -x side (parts: seat, legs, back)."""
    import trimesh

    def box(lo, hi):  # an axis-aligned box from its lowest to its highest corner
        return trimesh.creation.box(bounds=[lo, hi])

    s, w = SEAT["half"], LEG_WIDTH / 2
    post = s - LEG_INSET  # leg / post centres at x, y = +-post
    seat = box((-s, -s, SEAT["z0"]), (s, s, SEAT["z1"]))
    # Legs reach into the seat and back posts start inside it (no coplanar faces at the joints).
    legs = [
        box((x - w, y - w, 0.0), (x + w, y + w, SEAT["z0"] + 0.04))
        for x in (-post, post)
        for y in (-post, post)
    ]
    bx = -post  # the back's plane
    back = [
        box((bx - w, y - w, SEAT["z1"] - 0.03), (bx + w, y + w, BACK_TOP)) for y in (-post, post)
    ]
    d = RAIL_DEPTH / 2
    back += [box((bx - d, -post, z0), (bx + d, post, z1)) for z0, z1 in BACK_RAILS.values()]
    low, top = BACK_RAILS["low"][1] - 0.01, BACK_RAILS["top"][0] + 0.01  # slats: rail to rail
    sw, sd = SLAT_WIDTH / 2, SLAT_DEPTH / 2
    back += [box((bx - sd, y - sw, low), (bx + sd, y + sw, top)) for y in SLAT_Y]
    pieces = [(seat, 1, False)] + [(m, 2, False) for m in legs] + [(m, 3, False) for m in back]
    mesh = _assemble(pieces, {1: "seat", 2: "legs", 3: "back"}, _chair_colors)
    # Suggested edit: stretch the back upwards (plane just above the seat's top).
    return ProceduralObject(mesh, np.array([0.0, 0.0, 1.0, SEAT["z1"] + 0.02]), edit_part=1)


PROCEDURAL: dict[str, Callable[[], ProceduralObject]] = {
    "toycar": toycar,
    "figurine": figurine,
    "mug": mug,
    "chair": chair,
}


def build(name: str) -> ProceduralObject:
    """The procedural object called `name` (see PROCEDURAL)."""
    if name not in PROCEDURAL:
        raise SineError(f"unknown procedural object {name!r}; choose from {', '.join(PROCEDURAL)}")
    return PROCEDURAL[name]()
