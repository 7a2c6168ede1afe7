"""The batch file of `sine batch` (TOML) and the jobs it asks for.

A batch file lists captures and edits; each capture becomes a run directory OUT/NAME/run made by
the same stages a user runs by hand (`sine synth` when the capture is synthetic, `recon`, `fit`,
`features` when wanted), each edit a `sine edit` of one capture, and each output an orbit video
(`sine render`), a mesh (`sine export`) or a score against ground truth (`sine eval`). Stage
settings are the names `sine COMMAND --help-all` lists (the keys of the config.toml each stage
saves). Paths are relative to the batch file; `{capture}` stands for the capture's folder.

    [defaults]                 # settings every entry starts from (its own win)
    fit = { preset = "fast" }

    [[capture]]
    name = "car"               # OUT/car/
    source = "photos/car"      # or: synth = { procedural = "toycar", views = 24 }
    recon = { width = 256 }
    features = true            # or a table of `sine features` settings

    [[edit]]
    capture = "car"
    name = "taller"            # OUT/car/run/edits/taller, outputs in OUT/car/taller/
    mode = "geometry"          # geometry | texture | hybrid
    view = "r_013.png"         # a view's file name, or its index in the run's cameras
    target = "edited/r_013.png"
    outputs = ["video", "glb"] # video, glb, ply, obj
    eval = "{capture}/edits/geometric"   # a ground-truth folder to score against
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

from render.configs import tomllib
from render.errors import SineError

STAGE_SETTINGS = ("synth", "recon", "fit", "features", "edit", "render")  # [defaults] tables
CAPTURE_KEYS = ("name", "source", "synth", "recon", "fit", "features")
EDIT_KEYS = (
    "capture",
    "name",
    "mode",
    "view",
    "target",
    "mask",
    "region",
    "reference",
    "settings",
    "outputs",
    "eval",
    "render",
)
EDIT_FILES = ("target", "mask", "region", "reference")  # an edit's paths (become --FLAG PATH)
MESH_FORMATS = ("glb", "ply", "obj")
OUTPUTS = ("video", *MESH_FORMATS)
MODES = ("geometry", "texture", "hybrid")
RESERVED = ("run", "capture", "logs", "batch")  # folders of OUT/NAME/ an edit may not be named
ORBIT_FRAMES = 60  # `sine render`'s default orbit, when the batch asks for a video


@dataclass
class Job:
    """One stage of one object: a `sine` command and the jobs whose results it needs."""

    id: str  # "car/fit", "car/edit:taller", "car/video:taller"
    object: str  # the capture's name
    home: Path  # OUT/OBJECT: its run, logs/ and the batch's records (batch/)
    stage: str  # synth, recon, fit, features, edit, video, mesh, eval
    argv: list[str]  # the command and its arguments, as typed after `sine`
    settings: dict  # its settings (the batch file's tables; `--set` of each)
    result: Path  # the file the stage writes last (its "already done" evidence)
    deps: list[str] = field(default_factory=list)  # ids of the jobs that must finish first
    edit: str | None = None  # the edit's name, for the edit and its outputs
    view: str | int | None = None  # the edit's view; a file name is resolved after recon
    recorded: bool = False  # the batch skips it by its own record (stages that redo always)
    gpu: bool = False  # trains or renders (asks for a GPU where the cluster has them)

    @property
    def slug(self) -> str:
        """The job's file name stem under OUT/OBJECT/: "fit", "edit-taller"."""
        return self.id.split("/", 1)[1].replace(":", "-")


@dataclass
class Batch:
    """A batch file read and checked."""

    path: Path
    captures: list[dict]
    edits: list[dict]
    defaults: dict


def read_batch(path: str | Path) -> Batch:
    """Reads and checks the batch file's structure (a SineError naming the entry and key)."""
    path = Path(path)
    if not path.is_file():
        raise SineError(f"batch file {path} does not exist")
    try:
        data = tomllib.loads(path.read_text())
    except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
        raise SineError(f"{path} is not a readable TOML file ({exc})") from None
    unknown = sorted(set(data) - {"defaults", "capture", "edit"})
    if unknown:
        raise SineError(
            f"{path}: unknown table {unknown[0]!r}; a batch file has [defaults], "
            "[[capture]] and [[edit]]"
        )
    defaults = _table(data.get("defaults", {}), f"{path}: [defaults]")
    for key, value in defaults.items():
        if key not in STAGE_SETTINGS:
            raise SineError(f"{path}: [defaults] has {key!r}; use {', '.join(STAGE_SETTINGS)}")
        _table(value, f"{path}: [defaults] {key}")
    captures = [_check_capture(c, i, path) for i, c in enumerate(_entries(data, "capture", path))]
    if not captures:
        raise SineError(f"{path} lists no [[capture]]: nothing to do")
    names = [c["name"] for c in captures]
    for name in names:
        if names.count(name) > 1:
            raise SineError(f"{path}: two captures are named {name!r}; names must differ")
    edits = [_check_edit(e, i, path, names) for i, e in enumerate(_entries(data, "edit", path))]
    seen = [(e["capture"], e["name"]) for e in edits]
    for key in seen:
        if seen.count(key) > 1:
            raise SineError(f"{path}: capture {key[0]!r} has two edits named {key[1]!r}")
    return Batch(path, captures, edits, defaults)


def plan_jobs(batch: Batch, out: Path) -> list[Job]:
    """Every job of the batch, in an order where each job's dependencies come first."""
    out = Path(out).resolve()
    jobs: list[Job] = []
    for capture in batch.captures:
        edits = [e for e in batch.edits if e["capture"] == capture["name"]]
        jobs += _capture_jobs(batch, capture, edits, out)
        for edit in edits:
            jobs += _edit_jobs(batch, capture, edit, out)
    return jobs


def capture_folder(batch: Batch, capture: dict, out: Path) -> Path:
    """The capture of a batch entry: its source, or OUT/NAME/capture for a synthetic one."""
    if "synth" in capture:
        return Path(out) / capture["name"] / "capture"
    return _path(batch, capture["source"], None)


# ---- jobs ---------------------------------------------------------------------------------
def _capture_jobs(batch: Batch, capture: dict, edits: list[dict], out: Path) -> list[Job]:
    name, home = capture["name"], out / capture["name"]
    folder, run = capture_folder(batch, capture, out), home / "run"
    jobs = []
    if "synth" in capture:
        settings = _settings(batch, "synth", capture["synth"])
        argv = ["synth", "--out", str(folder), "--quiet"]
        jobs.append(
            Job(f"{name}/synth", name, home, "synth", argv, settings, folder / "synth.json")
        )
        jobs[-1].recorded = True
    jobs.append(
        Job(
            f"{name}/recon",
            name,
            home,
            "recon",
            ["recon", str(folder), "--out", str(run)],
            _settings(batch, "recon", capture.get("recon")),
            run / "recon_report.json",
            deps=[j.id for j in jobs],
        )
    )
    fit = Job(
        f"{name}/fit",
        name,
        home,
        "fit",
        ["fit", str(run), "--quiet"],
        _settings(batch, "fit", capture.get("fit")),
        run / "template" / "metrics.json",
        deps=[f"{name}/recon"],
        gpu=True,
    )
    jobs.append(fit)
    features = capture.get("features", False)
    if features is False and any(e["mode"] != "geometry" for e in edits):
        features = True  # texture and hybrid edits need the feature field
    if features is not False:
        jobs.append(
            Job(
                f"{name}/features",
                name,
                home,
                "features",
                ["features", str(run), "--quiet"],
                _settings(batch, "features", {} if features is True else features),
                run / "features" / "metrics.json",
                deps=[fit.id],
                gpu=True,
            )
        )
    return jobs


def _edit_jobs(batch: Batch, capture: dict, edit: dict, out: Path) -> list[Job]:
    name, obj, home = edit["name"], capture["name"], out / capture["name"]
    run, outputs = home / "run", home / name
    folder = capture_folder(batch, capture, out)
    argv = ["edit", str(run), "--mode", edit["mode"], "--name", name, "--quiet"]
    for key in EDIT_FILES:
        if key in edit:
            argv += [f"--{key}", str(_path(batch, edit[key], folder))]
    needs = f"{obj}/fit" if edit["mode"] == "geometry" else f"{obj}/features"
    learn = Job(
        f"{obj}/edit:{name}",
        obj,
        home,
        "edit",
        argv,
        _settings(batch, "edit", edit.get("settings")),
        run / "edits" / name / "metrics.json",
        deps=[needs],
        edit=name,
        view=edit["view"],
        gpu=True,
    )
    jobs = [learn]
    common = dict(deps=[learn.id], edit=name, recorded=True)
    if "video" in edit["outputs"]:
        render = {"orbit": ORBIT_FRAMES, **_settings(batch, "render", edit.get("render"))}
        video = outputs / "orbit.mp4"
        argv = ["render", str(run), "--edit", name, "--out", str(outputs / "orbit")]
        argv += ["--video", str(video), "--quiet"]
        jobs.append(Job(f"{obj}/video:{name}", obj, home, "video", argv, render, video, **common))
        jobs[-1].gpu = True
    for fmt in MESH_FORMATS:
        if fmt in edit["outputs"]:
            mesh = outputs / f"{name}.{fmt}"
            argv = ["export", str(run), "--edit", name, "--out", str(mesh)]
            jobs.append(Job(f"{obj}/{fmt}:{name}", obj, home, "mesh", argv, {}, mesh, **common))
    if "eval" in edit:
        gt, scores = _path(batch, edit["eval"], folder), outputs / "eval.json"
        argv = ["eval", str(run), "--edit", name, "--gt", str(gt), "--out", str(scores)]
        jobs.append(
            Job(f"{obj}/eval:{name}", obj, home, "eval", argv + ["--quiet"], {}, scores, **common)
        )
        jobs[-1].gpu = True
    return jobs


# ---- checks -------------------------------------------------------------------------------
def _entries(data: dict, key: str, path: Path) -> list[dict]:
    entries = data.get(key, [])
    if not isinstance(entries, list) or not all(isinstance(e, dict) for e in entries):
        raise SineError(f"{path}: write each {key} as a [[{key}]] table")
    return entries


def _table(value, what: str) -> dict:
    if not isinstance(value, dict):
        raise SineError(f"{what} must be a table of settings, e.g. {{ iterations = 300 }}")
    return value


def _name(value, what: str) -> str:
    if not isinstance(value, str) or not re.fullmatch(r"[A-Za-z0-9][A-Za-z0-9_.-]*", value):
        raise SineError(f"{what} needs a name of letters, digits, '_', '-' or '.' (got {value!r})")
    return value


def _check_capture(entry: dict, index: int, path: Path) -> dict:
    what = f"{path}: capture {entry.get('name', index + 1)!r}"
    _unknown_keys(entry, CAPTURE_KEYS, what)
    _name(entry.get("name"), f"{path}: [[capture]] number {index + 1}")
    if ("source" in entry) == ("synth" in entry):
        raise SineError(f'{what}: give either source = "FOLDER" or synth = {{ ... }}')
    if "source" in entry and not isinstance(entry["source"], str):
        raise SineError(f"{what}: source must be a path")
    for key in ("synth", "recon", "fit"):
        if key in entry:
            _table(entry[key], f"{what}: {key}")
    features = entry.get("features", False)
    if not isinstance(features, bool):
        _table(features, f"{what}: features (true, false or a table of settings)")
    return entry


def _check_edit(entry: dict, index: int, path: Path, captures: list[str]) -> dict:
    what = f"{path}: edit {entry.get('name', index + 1)!r}"
    _unknown_keys(entry, EDIT_KEYS, what)
    name = _name(entry.get("name"), f"{path}: [[edit]] number {index + 1}")
    if name in RESERVED:
        raise SineError(f"{what}: {', '.join(RESERVED)} are taken; choose another name")
    if entry.get("capture") not in captures:
        raise SineError(
            f"{what}: capture = {entry.get('capture')!r} is not a [[capture]] of the file "
            f"({', '.join(captures)})"
        )
    entry = {"mode": "geometry", "outputs": [], **entry}
    if entry["mode"] not in MODES:
        raise SineError(f"{what}: mode = {entry['mode']!r}; use {', '.join(MODES)}")
    view = entry.get("view")
    if not (isinstance(view, str) or (isinstance(view, int) and not isinstance(view, bool))):
        raise SineError(f'{what}: view = the edited view\'s file name ("r_013.png") or index')
    for key in EDIT_FILES + ("eval",):
        if key in entry and not isinstance(entry[key], str):
            raise SineError(f"{what}: {key} must be a path")
    outputs = entry["outputs"]
    if not isinstance(outputs, list) or any(o not in OUTPUTS for o in outputs):
        raise SineError(f"{what}: outputs = a list of {', '.join(OUTPUTS)} (got {outputs!r})")
    for key in ("settings", "render"):
        if key in entry:
            _table(entry[key], f"{what}: {key}")
    return entry


def _unknown_keys(entry: dict, allowed: tuple[str, ...], what: str) -> None:
    for key in entry:
        if key not in allowed:
            raise SineError(f"{what}: unknown key {key!r}; use {', '.join(allowed)}")


def _settings(batch: Batch, stage: str, own: dict | None) -> dict:
    """The [defaults] table of `stage` with the entry's own settings over it."""
    return {**batch.defaults.get(stage, {}), **(own or {})}


def _path(batch: Batch, text: str, capture: Path | None) -> Path:
    """A path of the batch file: `{capture}` replaced, relative to the file's folder."""
    if "{capture}" in text:
        if capture is None:
            raise SineError(f"{batch.path}: {{capture}} in {text!r} has no capture to stand for")
        text = text.replace("{capture}", str(capture))
    path = Path(text).expanduser()
    return path if path.is_absolute() else (batch.path.parent / path).resolve()
