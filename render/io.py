"""File IO shared by every stage: atomic writes, images, contact sheets, JSON/YAML, torch files.

Images inside the code are float32 RGB in [0, 1], HWC. Every artefact is written to a temporary
file in the destination folder first and then renamed, so an interrupted run never leaves a
half-written file behind. Torch files (checkpoints, fields) are read with `weights_only=True`:
they hold tensors and plain values only (configs as JSON text), so opening a run directory
someone shared never executes pickled code.
"""

from __future__ import annotations

import contextlib
import errno
import json
import os
import pickle
import re
import tempfile
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import yaml

from render.errors import SineError

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff", ".ppm", ".pgm", ".webp")


def _umask() -> int:
    """The process's umask (read without changing it where /proc says it)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def write_error(path: str | os.PathLike, exc: OSError) -> SineError:
    """A disk full, a read-only or protected folder while writing `path`, as one readable line
    (finished results are never replaced by a half-written file)."""
    denied = "permission denied: make the folder writable, or write somewhere else"
    why = {
        errno.ENOSPC: "no space left on the device: free some space, then run this again; "
        "finished results are kept",
        errno.EDQUOT: "the disk quota is exhausted: free some space, then run this again; "
        "finished results are kept",
        errno.EROFS: "the file system is read-only: write somewhere else",
        errno.EACCES: denied,
        errno.EPERM: denied,
    }.get(exc.errno, exc.strerror or type(exc).__name__)
    return SineError(f"cannot write {path} ({why})")


WRITE_ERRORS = (errno.ENOSPC, errno.EDQUOT, errno.EROFS, errno.EACCES, errno.EPERM)


# the temporary file `atomic_path` writes before the rename: ".STEM.<8 random characters>SUFFIX"
_PARTIAL_WRITE = re.compile(r"^\..+\.[a-z0-9_]{8}(\.[A-Za-z0-9]+)?$")


def remove_partial_writes(
    folder: str | os.PathLike, recursive: bool = True, of: str | os.PathLike | None = None
) -> int:
    """Deletes the temporary files that writers killed mid-write (kill -9, power loss) left in
    `folder` (only those of the file `of`, when given); returns how many. Only for what the
    caller holds the lock of (a writer at work there would lose its file)."""
    folder = Path(folder)
    if not folder.is_dir():
        return 0
    start, end = (f".{Path(of).stem}.", Path(of).suffix) if of is not None else (".", "")
    found = [
        p
        for p in (folder.rglob(start + "*") if recursive else folder.glob(start + "*"))
        if p.is_file()
        and _PARTIAL_WRITE.match(p.name)
        and p.name.endswith(end)
        and not p.name.endswith(".lock")
    ]
    for p in found:
        p.unlink(missing_ok=True)
    return len(found)


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike):
    """Yields a temporary path beside `path`; renames it onto `path` if the block succeeds.

    The file gets the mode a plain `open()` would give it (0644 under the usual umask 0022).
    A full disk or a folder that cannot be written is a SineError naming `path`."""
    path = Path(path)
    if path.is_dir():
        raise SineError(f"{path} is a folder: give the name of a file to write")
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    except OSError as exc:
        if exc.errno in WRITE_ERRORS:
            raise write_error(path, exc) from None
        raise
    os.fchmod(fd, 0o666 & ~_umask())
    os.close(fd)
    try:
        yield Path(tmp)
        os.replace(tmp, path)
    except OSError as exc:
        if exc.errno in WRITE_ERRORS:
            raise write_error(path, exc) from None
        raise
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
    import shutil

    import torch

    with atomic_path(path) as tmp:
        try:
            torch.save(obj, tmp)
        except RuntimeError as exc:  # torch's writer reports a failed write this way
            if shutil.disk_usage(Path(tmp).parent).free < (64 << 20):
                raise write_error(path, OSError(errno.ENOSPC, "No space left on device")) from None
            raise SineError(f"cannot write {path} ({str(exc).splitlines()[0]})") from None


TORCH_READ_ERRORS = (RuntimeError, OSError, EOFError, ValueError, pickle.UnpicklingError)


def torch_read_problem(exc: BaseException) -> str:
    """What is wrong with a torch file that did not load, in a few words (torch's own message
    is long and advises an unsafe way to load the file)."""
    text = str(exc)
    if "Weights only load failed" in text or isinstance(exc, pickle.UnpicklingError):
        return "it holds Python objects, which are never loaded from a file"
    if isinstance(exc, EOFError) or "central directory" in text or "truncated" in text.lower():
        return "it is truncated or corrupt"
    if isinstance(exc, OSError):
        return exc.strerror or "it cannot be read"
    return "it is corrupt or not a file of this program"


def load_torch(path: str | os.PathLike, rebuild: str | None = None) -> Any:
    """torch.load(path, weights_only=True) onto the CPU. A missing or unreadable file (corrupt,
    truncated, or holding pickled Python objects) is a SineError that names it and `rebuild`,
    the command that makes it again."""
    import torch

    path = Path(path)
    rebuild = rebuild or "the command that wrote it, with --force"
    try:
        return torch.load(path, map_location="cpu", weights_only=True)
    except FileNotFoundError:
        raise SineError(f"{path} does not exist; make it with {rebuild}") from None
    except TORCH_READ_ERRORS as exc:
        why = torch_read_problem(exc)
        raise SineError(f"cannot read {path}: {why}; make it again with {rebuild}") from None


def read_triangle_mesh(path: str | os.PathLike, rebuild: str):
    """An Open3D triangle mesh from a file, refused (a SineError naming `rebuild`, the command
    that makes it again) when it is missing, has no triangles or is truncated: Open3D only
    prints a warning for a PLY cut short and returns what it read, so the counts in the PLY's
    header are checked."""
    import open3d as o3d

    path = Path(path)
    if not path.is_file():
        raise SineError(f"{path} does not exist; make it with {rebuild}")
    quiet = o3d.utility.VerbosityContextManager(o3d.utility.VerbosityLevel.Error)
    with quiet, _native_stderr_silenced():  # its reader's complaints: the check below says it
        mesh = o3d.io.read_triangle_mesh(str(path))
    vertices, faces = _ply_counts(path)
    complete = vertices is None or (len(mesh.vertices) == vertices and len(mesh.triangles) >= faces)
    if len(mesh.triangles) == 0 or not complete:
        raise SineError(
            f"cannot read {path}: it is truncated or corrupt; make it again with {rebuild}"
        )
    return mesh


@contextlib.contextmanager
def _native_stderr_silenced():
    """Discards what native code writes to the process's stderr (fd 2) during the block."""
    import sys

    sys.stderr.flush()
    saved = os.dup(2)
    try:
        with open(os.devnull, "wb") as null:
            os.dup2(null.fileno(), 2)
        yield
    finally:
        os.dup2(saved, 2)
        os.close(saved)


def _ply_counts(path: Path) -> tuple[int | None, int | None]:
    """(vertex, face) counts a PLY file's header announces; (None, None) for other files."""
    with open(path, "rb") as f:
        if f.readline().strip() != b"ply":
            return None, None
        counts = {}
        for line in f:
            words = line.split()
            if words[:1] == [b"end_header"]:
                break
            if words[:1] == [b"element"] and len(words) == 3:
                counts[words[1].decode(errors="replace")] = int(words[2])
    return counts.get("vertex", 0), counts.get("face", 0)


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
