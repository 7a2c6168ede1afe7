"""File IO shared by every stage: atomic writes, images, contact sheets, JSON/YAML, torch files.

Images inside the code are float32 RGB in [0, 1], HWC. Every artefact is written to a temporary
file in the destination folder first and then renamed, so an interrupted run never leaves a
half-written file behind. Torch files (checkpoints, fields) are read with `weights_only=True`:
they hold tensors and plain values only (configs as JSON text), so opening a run directory
someone shared never executes pickled code.
"""

from __future__ import annotations

import contextlib
import json
import os
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from render.errors import SineError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yields a temporary path beside `path`; renames it onto `path` if the block succeeds."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.remove(tmp)


def require_directory(path: str | os.PathLike, option: str = "--out") -> Path:
    """`path` as a folder to write into: fine when missing or a folder; a SineError when it names
    an existing file."""
    path = Path(path)
    if path.exists() and not path.is_dir():
        raise SineError(f"{option} {path} is an existing file; give a folder (new or existing)")
    return path


def file_sha256(path: str | os.PathLike) -> str:
    """Hex SHA-256 of a file's bytes (read in 1 MiB chunks)."""
    import hashlib

    h = hashlib.sha256()
    with open(path, "rb") as f:
        for chunk in iter(lambda: f.read(1 << 20), b""):
            h.update(chunk)
    return h.hexdigest()


def artefact_digest(path: str | os.PathLike) -> str | None:
    """Hex SHA-256 of a file, or of a folder's files (their relative paths and contents, in
    order); None when `path` does not exist."""
    import hashlib

    path = Path(path)
    if path.is_file():
        return file_sha256(path)
    if not path.is_dir():
        return None
    h = hashlib.sha256()
    for file in sorted(p for p in path.rglob("*") if p.is_file()):
        h.update(f"{file.relative_to(path).as_posix()}\0{file_sha256(file)}\n".encode())
    return h.hexdigest()


def write_bytes_atomic(path: str | os.PathLike, data: bytes) -> None:
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def write_text_atomic(path: str | os.PathLike, text: str) -> None:
    write_bytes_atomic(path, text.encode("utf-8"))


def write_json(path: str | os.PathLike, obj: Any) -> None:
    write_text_atomic(path, json.dumps(to_jsonable(obj), indent=2) + "\n")


def read_json(path: str | os.PathLike) -> Any:
    path = Path(path)
    try:
        return json.loads(path.read_text())
    except FileNotFoundError:
        raise SineError(f"{path} does not exist") from None
    except json.JSONDecodeError as exc:
        raise SineError(f"{path} is not valid JSON ({exc})") from None


def write_yaml(path: str | os.PathLike, obj: Any) -> None:
    write_text_atomic(path, yaml.safe_dump(to_jsonable(obj), sort_keys=False))


def read_yaml(path: str | os.PathLike) -> Any:
    return yaml.safe_load(Path(path).read_text())


def to_jsonable(obj: Any) -> Any:
    """numpy arrays/scalars and Paths -> plain Python, recursively."""
    if isinstance(obj, dict):
        return {str(k): to_jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [to_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, Path):
        return str(obj)
    return obj


def read_image(path: str | os.PathLike) -> np.ndarray:
    """Reads an image as float32 RGB in [0, 1], [H, W, 3]. Alpha is dropped."""
    path = Path(path)
    if not path.is_file():
        raise SineError(f"image {path} does not exist")
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SineError(f"cannot read {path} as an image (corrupt or unsupported format)")
    return _to_float_rgb(raw)


def read_image_rgba(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray | None]:
    """Reads an image as float32 RGB [H, W, 3] and its alpha [H, W] in [0, 1] (None if opaque)."""
    path = Path(path)
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SineError(f"cannot read {path} as an image (missing, corrupt or unsupported format)")
    alpha = None
    if raw.ndim == 3 and raw.shape[2] == 4:
        scale = 65535.0 if raw.dtype == np.uint16 else 255.0
        alpha = raw[..., 3].astype(np.float32) / scale
    return _to_float_rgb(raw), alpha


def _to_float_rgb(raw: np.ndarray) -> np.ndarray:
    scale = 65535.0 if raw.dtype == np.uint16 else 255.0
    img = raw.astype(np.float32) / scale
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=2)
    elif img.shape[2] == 4:
        img = img[..., :3]
    return np.ascontiguousarray(img[..., ::-1])  # BGR -> RGB


def write_image(path: str | os.PathLike, image: np.ndarray) -> None:
    """Writes float RGB [H, W, 3] in [0, 1] (or uint8) as an 8-bit image, atomically."""
    image = np.asarray(image)
    if image.dtype != np.uint8:
        image = (np.clip(image, 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)
    if image.ndim == 3:
        image = image[..., ::-1]  # RGB -> BGR
    _write_cv(path, image)


def contact_sheet(tiles: list[np.ndarray], columns: int, fill: float = 1.0) -> np.ndarray:
    """Thumbnails [h_i, w, 3] in rows of `columns` -> one image [rows * h, columns * w, 3];
    shorter tiles and the empty cells of the last row are filled with `fill`."""
    th = max(t.shape[0] for t in tiles)
    tiles = [np.pad(t, ((0, th - t.shape[0]), (0, 0), (0, 0)), constant_values=fill) for t in tiles]
    while len(tiles) % columns:
        tiles.append(np.full_like(tiles[0], fill))
    return np.vstack([np.hstack(tiles[i : i + columns]) for i in range(0, len(tiles), columns)])


def save_torch(path: str | os.PathLike, obj: Any) -> None:
    """torch.save, atomically; `obj` should hold only tensors and plain values (see load_torch)."""
    import torch

    with atomic_path(path) as tmp:
        torch.save(obj, tmp)


def load_torch(path: str | os.PathLike) -> Any:
    """torch.load(path, weights_only=True) onto the CPU; an unreadable file (corrupt, truncated,
    or holding pickled Python objects) is a SineError that names it."""
    import pickle

    import torch

    path = Path(path)
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise SineError(f"{path} does not exist") from None
    except (RuntimeError, OSError, EOFError, pickle.UnpicklingError) as exc:
        why = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:200]
        raise SineError(f"cannot read {path} ({why}); delete it or re-run with --force") from None


def write_mask(path: str | os.PathLike, mask: np.ndarray) -> None:
    """Writes a boolean / [0,1] mask [H, W] as a 0/255 PNG."""
    _write_cv(path, (np.asarray(mask) > 0.5).astype(np.uint8) * 255)


def read_mask(path: str | os.PathLike) -> np.ndarray:
    """Reads a mask PNG as bool [H, W] (any channel > half range is foreground)."""
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SineError(f"cannot read mask {path}")
    if raw.ndim == 3:
        raw = raw[..., 3] if raw.shape[2] == 4 else raw.max(axis=2)
    half = 32767 if raw.dtype == np.uint16 else 127
    return raw > half


def write_label_map(path: str | os.PathLike, labels: np.ndarray) -> None:
    """Writes an integer label map [H, W] (0 = background) as a 16-bit PNG."""
    _write_cv(path, np.asarray(labels).astype(np.uint16))


def read_label_map(path: str | os.PathLike) -> np.ndarray:
    raw = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if raw is None:
        raise SineError(f"cannot read label map {path}")
    return raw.astype(np.int32)


def write_depth(path: str | os.PathLike, depth: np.ndarray) -> None:
    """Writes a depth map [H, W] (float32, 0 = no depth) as .npy, atomically."""
    with atomic_path(path) as tmp:
        with open(tmp, "wb") as f:
            np.save(f, np.asarray(depth, dtype=np.float32))


def read_depth(path: str | os.PathLike) -> np.ndarray:
    return np.load(path).astype(np.float32)


def _write_cv(path: str | os.PathLike, array: np.ndarray) -> None:
    path = Path(path)
    ok, buf = cv2.imencode(path.suffix or ".png", array)
    if not ok:
        raise SineError(f"cannot encode an image for {path}")
    write_bytes_atomic(path, buf.tobytes())
