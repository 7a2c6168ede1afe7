"""The per-format capture readers of `sine ingest` (READERS: format name -> reader): folders
of images, videos, transforms.json / NeRF-synthetic split files, COLMAP models, Middlebury
rings, NeuS/IDR folders and images with projection matrices; each gives a Capture
(recon.capture_formats)."""

from __future__ import annotations

from collections import Counter
from pathlib import Path
from typing import TYPE_CHECKING

import cv2
import numpy as np

from recon.capture_formats import (
    MIN_VIEWS,
    SPLIT_FILES,
    Capture,
    SourceView,
    _find_colmap_model,
    _image_files,
    _image_folder,
    _probe_files,
    _projection_file,
    _short_list,
    detect_format,
)
from render.cameras import (
    camera_from_krt,
    camera_from_projection,
    cameras_from_neus,
    cameras_from_transforms,
    read_colmap_model,
    read_middlebury_par,
)
from render.errors import SineError
from render.io import IMAGE_SUFFIXES, read_json

if TYPE_CHECKING:
    from recon.ingest import IngestConfig


def _read_capture(fmt: str, capture: Path, cfg: IngestConfig) -> Capture:
    """The format's reader; with --ignore-poses a pose file it cannot use is no error: the
    images are read alone (SfM then estimates the intrinsics too)."""
    try:
        return READERS[fmt](capture, cfg)
    except SineError as exc:
        if not cfg.ignore_poses or fmt in ("images", "video"):
            raise
        folder = capture if capture.is_dir() else capture.parent
        try:
            cap = _read_images(folder, cfg)
        except SineError:
            raise exc from None
        note = f"the {fmt} cameras could not be used ({exc}); --ignore-poses: images only"
        print(f"[ingest] {note}")
        cap.notes.append(note)
        return cap


# ---- format readers -----------------------------------------------------------------------
def _read_images(capture: Path, cfg: IngestConfig) -> Capture:
    if not capture.is_dir():
        raise SineError(f"format 'images' needs a folder of images; {capture} is not a folder")
    folder = _image_folder(capture)
    if folder is None:
        detect_format(capture)  # raises the detailed "empty / no images" message
        raise SineError(f"no images found in {capture}")
    files = _image_files(folder)
    views = [SourceView(p.stem, str(p), path=p) for p in files]
    notes = []
    ignored = sorted(p.name for p in capture.glob("*.mat"))
    if ignored:
        notes.append(f"ignored {', '.join(ignored)} (not a metric calibration we can use)")
    return Capture("images", views, has_poses=False, notes=notes)


def _read_video(capture: Path, cfg: IngestConfig) -> Capture:
    if not capture.is_file():
        raise SineError(f"format 'video' needs a video file; {capture} is not a file")
    cap = cv2.VideoCapture(str(capture))
    if not cap.isOpened():
        raise SineError(
            f"cannot open video {capture}: OpenCV has no decoder for it or the file is damaged; "
            "convert it to MP4 (H.264) or extract the frames to a folder of images"
        )
    try:
        count = int(cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if count <= 0:  # some containers do not know: count by decoding
            count = 0
            while cap.grab():
                count += 1
            cap.release()
            cap = cv2.VideoCapture(str(capture))
        if count == 0:
            raise SineError(f"video {capture} has no frames that OpenCV can decode")
        wanted = np.unique(np.round(np.linspace(0, count - 1, min(cfg.frames, count))).astype(int))
        wanted_set = set(wanted.tolist())
        views, index = [], 0
        while len(views) < len(wanted) and cap.grab():
            if index in wanted_set:
                ok, frame = cap.retrieve()
                if ok and frame is not None:
                    views.append(
                        SourceView(
                            f"{capture.stem}_{index:05d}",
                            f"{capture}#frame={index}",
                            frame=np.ascontiguousarray(frame),
                        )
                    )
            index += 1
    finally:
        cap.release()
    notes = [f"sampled {len(views)} of {count} frames evenly"]
    return Capture("video", views, has_poses=False, notes=notes)


def _read_transforms(capture: Path, cfg: IngestConfig) -> Capture:
    split_folder = capture.is_dir() and not (capture / "transforms.json").is_file()
    if split_folder and (capture / SPLIT_FILES[0][0]).is_file():
        return _read_split_transforms(capture)
    path = capture / "transforms.json" if capture.is_dir() else capture
    if not path.is_file():
        raise SineError(f"format 'transforms' needs a transforms.json; {path} does not exist")
    views, notes = _transforms_views(path)
    return Capture("transforms", views, has_poses=True, notes=notes)


def _read_split_transforms(folder: Path) -> Capture:
    """A NeRF-synthetic (Blender) folder: the frames of every split file present, each image
    once (the first file listing it gives its split; see SPLIT_FILES)."""
    views, notes, seen, repeated = [], [], set(), Counter()
    for name, split in SPLIT_FILES:
        path = folder / name
        if not path.is_file():
            continue
        minimum = MIN_VIEWS if split == "train" else 0
        file_views, file_notes = _transforms_views(path, minimum)
        notes += file_notes
        for view in file_views:
            key = view.path.resolve()
            if key in seen:
                repeated[name] += 1
                continue
            seen.add(key)
            view.split = split
            views.append(view)
    counts = Counter(v.split for v in views)
    notes.append(
        f"splits from the NeRF-synthetic split files: {counts['train']} train, "
        f"{counts['test']} test (held out)"
    )
    for name, n in repeated.items():
        notes.append(f"{name} repeats {n} image(s) of an earlier split file: counted once")
    return Capture("transforms", views, has_poses=True, notes=notes)


def _transforms_views(path: Path, minimum: int = MIN_VIEWS) -> tuple[list[SourceView], list[str]]:
    """The views of one transforms.json-style file and its notes (images it lists that do not
    exist are skipped with a warning unless fewer than `minimum` remain)."""
    data = read_json(path)
    if not isinstance(data, dict) or not isinstance(data.get("frames"), list):
        raise SineError(
            f"unknown camera format: {path} is JSON but not a NeRF/nerfstudio transforms.json "
            "(no 'frames' list)"
        )
    base = path.parent
    files: dict[str, Path] = {}
    missing = []
    for frame in data["frames"]:
        if "file_path" not in frame:
            raise SineError(f"{path}: every frame needs a 'file_path'")
        found = _resolve_image(base, frame["file_path"])
        if found is None:
            missing.append(frame["file_path"])
        else:
            files[frame["file_path"]] = found
    notes = _missing_note(path, missing, len(files), f"paths are relative to {base}", minimum)
    if missing:
        data = {**data, "frames": [f for f in data["frames"] if f["file_path"] in files]}
    if not data["frames"] and minimum == 0:
        return [], notes
    sizes = _probe_files(list(files.values()))
    image_sizes = {fp: sizes[p] for fp, p in files.items()}
    cams = cameras_from_transforms(data, image_sizes)
    depth_scale = float(data.get("depth_unit_scale_factor", 1e-3))
    views = []
    for frame, (fp, cam) in zip(data["frames"], cams, strict=True):
        view = SourceView(files[fp].stem, str(files[fp]), path=files[fp], camera=cam)
        for key, attr in (("mask_path", "mask"), ("depth_file_path", "depth")):
            if frame.get(key):
                p = base / frame[key]
                if not p.is_file():
                    raise SineError(f"{path}: {key} {frame[key]} of {fp} does not exist")
                setattr(view, attr, p)
        view.depth_scale = depth_scale
        views.append(view)
    return views, notes


def _read_colmap(capture: Path, cfg: IngestConfig) -> Capture:
    model = _find_colmap_model(capture)
    if model is None:
        raise SineError(
            f"no COLMAP model in {capture}: expected cameras.bin/txt + images.bin/txt in it or "
            "in sparse/0"
        )
    cams = read_colmap_model(model)
    if not cams:
        raise SineError(f"the COLMAP model in {model} has no registered images")
    image_dir = None
    for cand in (model, model.parent, model.parent.parent, model.parent.parent.parent):
        for d in (cand / "images", cand):
            if (d / cams[0][0]).is_file():
                image_dir = d
                break
        if image_dir is not None:
            break
    if image_dir is None:
        raise SineError(
            f"cannot find the images of the COLMAP model {model} (looked for {cams[0][0]} in an "
            "images/ folder beside or above it)"
        )
    missing = [n for n, _ in cams if not (image_dir / n).is_file()]
    cams = [(n, c) for n, c in cams if (image_dir / n).is_file()]
    views = [
        SourceView(Path(n).stem, str(image_dir / n), path=image_dir / n, camera=c) for n, c in cams
    ]
    notes = [f"COLMAP model {model}", *_missing_note(model, missing, len(cams), str(image_dir))]
    unregistered = len(_image_files(image_dir, strict=False)) - len(cams)
    if unregistered > 0:
        notes.append(f"{unregistered} image(s) in {image_dir} have no pose in the model: skipped")
    return Capture("colmap", views, has_poses=True, notes=notes)


def _read_middlebury(capture: Path, cfg: IngestConfig) -> Capture:
    pars = sorted(capture.glob("*_par.txt")) if capture.is_dir() else [capture]
    if not pars:
        raise SineError(f"format 'middlebury' needs a *_par.txt in {capture}")
    rows = read_middlebury_par(pars[0])
    base = pars[0].parent
    missing = [name for name, *_ in rows if not (base / name).is_file()]
    rows = [row for row in rows if (base / row[0]).is_file()]
    sizes = _probe_files([base / name for name, *_ in rows])
    views = []
    for name, K, R, t in rows:
        w, h = sizes[base / name]
        cam = camera_from_krt(K, R, t, w, h, name)
        views.append(SourceView(Path(name).stem, str(base / name), path=base / name, camera=cam))
    notes = [f"cameras from {pars[0].name}"] + (
        [f"ignored {', '.join(p.name for p in pars[1:])}"] if len(pars) > 1 else []
    )
    notes += _missing_note(pars[0], missing, len(rows), str(base))
    return Capture("middlebury", views, has_poses=True, notes=notes)


def _read_neus(capture: Path, cfg: IngestConfig) -> Capture:
    root = capture.parent if capture.is_file() else capture
    npz_path = root / "cameras_sphere.npz"
    if not npz_path.is_file():
        raise SineError(f"format 'neus' needs {npz_path}")
    image_dir = next((root / d for d in ("image", "images") if (root / d).is_dir()), None)
    if image_dir is None:
        raise SineError(f"NeuS/IDR capture {root} has no image/ (or images/) folder")
    files = _image_files(image_dir)
    sizes = _probe_files(files)
    with np.load(npz_path) as npz:
        cams, scale_mat = cameras_from_neus(npz, [sizes[p] for p in files])
    mask_dir = next((root / d for d in ("mask", "masks") if (root / d).is_dir()), None)
    masks = _image_files(mask_dir) if mask_dir else []
    by_stem = {p.stem: p for p in masks}
    views = []
    for i, (p, cam) in enumerate(zip(files, cams, strict=True)):
        mask = by_stem.get(p.stem) or (masks[i] if len(masks) == len(files) else None)
        views.append(SourceView(p.stem, str(p), path=p, camera=cam.replace(name=p.name), mask=mask))
    r, c = float(scale_mat[0, 0]), scale_mat[:3, 3]
    extra = {"source_normalization": {"scale": 1.0 / r, "center": [float(x) for x in c]}}
    return Capture("neus", views, has_poses=True, extra=extra)


def _read_projections(capture: Path, cfg: IngestConfig) -> Capture:
    folder = _image_folder(capture) if capture.is_dir() else None
    if folder is None:
        raise SineError(f"format 'projections' needs a folder of images; none in {capture}")
    files = _image_files(folder)
    pfiles = {p: _projection_file(p) for p in files}
    missing = [p.name for p, q in pfiles.items() if q is None]
    if missing:
        raise SineError(
            f"no projection matrix file (<stem>_P.txt or <stem>.P) for {_short_list(missing)} "
            f"in {folder}: give one per image, or remove the others to ingest images only"
        )
    shared = [q.name for q, n in Counter(pfiles.values()).items() if n > 1]
    if shared:
        raise SineError(
            f"several images match the same projection file ({_short_list(shared)}) in "
            f"{folder}: name them so that each image has its own <stem>_P.txt"
        )
    sizes = _probe_files(files)
    views = []
    for p in files:
        P = _read_projection_matrix(pfiles[p])
        cam = camera_from_projection(P, *sizes[p], name=p.name)
        views.append(SourceView(p.stem, str(p), path=p, camera=cam))
    return Capture("projections", views, has_poses=True)


READERS = {
    "images": _read_images,
    "video": _read_video,
    "transforms": _read_transforms,
    "colmap": _read_colmap,
    "middlebury": _read_middlebury,
    "neus": _read_neus,
    "projections": _read_projections,
}


def _missing_note(
    source: Path, missing: list[str], present: int, where: str, minimum: int = MIN_VIEWS
) -> list[str]:
    """A warning (printed and kept in captures.json's notes) for images a pose file lists that
    do not exist: the capture goes on with the ones that do, unless fewer than `minimum`."""
    if not missing:
        return []
    if present < minimum:
        raise SineError(
            f"{source} lists {len(missing) + present} images but only {present} exist "
            f"({where}; missing: {_short_list(missing)}); a reconstruction needs at least "
            f"{MIN_VIEWS}: put the images beside it"
        )
    note = (
        f"warning: {len(missing)} image(s) listed in {Path(source).name} do not exist "
        f"({_short_list(missing)}); using the {present} that do"
    )
    print(f"[ingest] {note}")
    return [note]


def _read_projection_matrix(path: Path) -> np.ndarray:
    values = []
    for token in path.read_text().split():
        try:
            values.append(float(token))
        except ValueError:
            continue  # headers such as "CONTOUR"
    if len(values) != 12:
        raise SineError(
            f"{path}: expected the 12 numbers of a 3x4 projection matrix, found {len(values)}"
        )
    return np.array(values).reshape(3, 4)


def _resolve_image(base: Path, file_path: str) -> Path | None:
    p = base / file_path
    if p.is_file():
        return p
    if not p.suffix or p.suffix.lower() not in IMAGE_SUFFIXES:  # NeRF blender: "./train/r_0"
        for suffix in (".png", *IMAGE_SUFFIXES):
            q = p.with_name(p.name + suffix)
            if q.is_file():
                return q
    return None
