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

The pieces: `recon.synth_mesh` (loading, normalising), `recon.synth_edits` (the GT edits),
`recon.synth_render` (cameras, backdrops, rendering), `recon.synth_output` (the output layouts);
this module holds the configuration and `synthesize`, which runs them.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from recon import procedural
from recon.mesh_data import MeshData
from recon.mesh_data import sample_texture as sample_texture  # re-exported
from recon.synth_edits import (
    DECAL_PATTERNS,
    EDIT_KINDS,
    GEOMETRIC_OPERATIONS,
    GT_DISPLACEMENT_FILE,
    TEXTURE_OPERATIONS,
    _edited_meshes,
    _save_gt_mesh,
    gt_mesh,
)
from recon.synth_mesh import (
    OBJECT_RADIUS,
    UP_AXES,
    Normalisation,
    load_mesh_file,
    normalise,
    normalised_plane,
    resolve_up_axis,
)
from recon.synth_output import (
    NERF_SYNTHETIC_DIR,
    OUTPUT_FORMATS,
    write_nerf_synthetic,
    write_views,
)
from recon.synth_render import (
    DEFAULT_LIGHTS,
    fit_camera_distance,
    make_backdrop,
    parse_background,
    render_views,
    ring_cameras,
)
from render.cameras import Camera, load_cameras
from render.configs import option, to_dict
from render.errors import SineError
from render.io import write_json


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
