"""Coloured meshes out: vertex colours from a radiance field, the capture's units, PLY/GLB/OBJ.

Vertex colour = what a camera looking straight at the surface sees there: a short ray along
the vertex's inward normal through the vertex, from `band` outside to `band` inside (the proxy
band the field was trained in), volume rendered with the field. Rays with almost no opacity
(the proxy and the field disagree there) take the colour queried at the vertex itself.

Run units -> capture units: cameras.json stores x_run = scale * rotation @ (x_in - center), so
x_in = rotation^T @ x_run / scale + center (a similarity: triangle winding is kept).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from render import volume
from render.errors import SineError
from render.io import atomic_path

MESH_SUFFIXES = (".ply", ".glb", ".obj")


def surface_colors(
    field_query,
    points: np.ndarray,
    normals: np.ndarray,
    band: float = 0.04,
    samples: int = 16,
    chunk: int = 8192,
    device: torch.device | None = None,
) -> np.ndarray:
    """Colours [N, 3] in [0, 1] seen along -normal at `points` [N, 3] (unit `normals` [N, 3]).

    `field_query(x [M, 3], d [M, 3]) -> {"sigma": [M], "rgb": [M, 3], ...}` (any field).
    """
    device = device or torch.device("cpu")
    points = np.asarray(points, np.float32).reshape(-1, 3)
    normals = np.asarray(normals, np.float32).reshape(-1, 3)
    step = 2.0 * band / samples
    t = (torch.arange(samples, dtype=torch.float32, device=device) + 0.5) * step  # [S]
    out = np.zeros((len(points), 3), np.float32)
    with torch.no_grad():
        for start in range(0, len(points), chunk):
            p = torch.from_numpy(points[start : start + chunk]).to(device)  # [R, 3]
            n = torch.from_numpy(normals[start : start + chunk]).to(device)
            d = -n
            x = (p + band * n)[:, None, :] + d[:, None, :] * t[None, :, None]  # [R, S, 3]
            res = field_query(x.reshape(-1, 3), d.repeat_interleave(samples, 0))
            sigma = res["sigma"].view(len(p), samples)
            rgb = res["rgb"].view(len(p), samples, 3)
            w = volume.render_weights(sigma, t.expand_as(sigma), delta=torch.full_like(sigma, step))
            acc = volume.opacity(w)  # [R]
            color = (w[..., None] * rgb).sum(1) / acc.clamp_min(1e-6)[:, None]
            at_point = rgb[:, samples // 2]  # the sample next to the vertex
            color = torch.where((acc > 0.05)[:, None], color, at_point)
            out[start : start + len(p)] = color.clamp(0, 1).float().cpu().numpy()
    return out


def denormalize_points(
    points: np.ndarray, scale: float, center: np.ndarray, rotation: np.ndarray | None = None
) -> np.ndarray:
    """Run units [N, 3] -> capture units: rotation^T @ x / scale + center."""
    rotation = np.eye(3) if rotation is None else np.asarray(rotation, np.float64).reshape(3, 3)
    x = np.asarray(points, np.float64).reshape(-1, 3)
    return (x @ rotation) / float(scale) + np.asarray(center, np.float64).reshape(3)


def save_colored_mesh(
    path: str | Path, vertices: np.ndarray, triangles: np.ndarray, colors: np.ndarray
) -> None:
    """Writes a mesh with per-vertex colours [V, 3] in [0, 1] as .ply, .glb or .obj (trimesh).

    Vertices are kept as given (no merging or reordering), so indices match the input.
    """
    import trimesh

    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise SineError(f"{path}: mesh format must be one of {', '.join(MESH_SUFFIXES)}")
    rgba = np.concatenate(
        [
            (np.clip(colors, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8),
            np.full((len(colors), 1), 255, np.uint8),
        ],
        axis=1,
    )
    mesh = trimesh.Trimesh(
        vertices=np.asarray(vertices, np.float64),
        faces=np.asarray(triangles, np.int64),
        vertex_colors=rgba,
        process=False,
    )
    with atomic_path(path) as tmp:
        if suffix == ".obj":
            data = trimesh.exchange.obj.export_obj(mesh, include_color=True, include_texture=False)
            Path(tmp).write_text(data)
        else:
            mesh.export(str(tmp), file_type=suffix[1:])
