"""Reliability of the `sine` CLI against bad inputs and faults: does every refusal come as one
readable line, fast, without a traceback, without touching finished work and without debris?

    .venv/bin/python bench/bench_faults.py [--out DIR] [--keep] [--only WORD]

Builds a tiny fixture (`sine synth` toycar, 8 views of 64x64; the ground-truth mesh as proxy; a
tiny `sine fit`, a tiny `sine features` and one finished tiny geometry edit "base"), or reuses
the one under --out DIR, then runs a fixed catalogue of bad inputs and faults, each as a
subprocess of the `sine` CLI on a fresh copy of the fixture (DIR/cases/NN/: run/, capture/ and
the case's own files). Families of cases:

- plain: missing/corrupt/truncated inputs, absurd or contradictory options;
- readonly: the command runs in a private mount namespace where the run (or the output folder)
  is a read-only bind mount (the bench runs as root, whom file modes do not stop; the venv's
  interpreter lives under /root, so an unprivileged user cannot run it at all);
- diskfull: the run (copied onto a tmpfs with 64 KiB to spare) or the output folder (a 4 KiB
  tmpfs) fills up while the command writes;
- concurrent: two identical `sine edit` processes on one new edit name at once;
- interrupt: SIGINT or SIGKILL to `sine edit/fit --force` over a finished artefact, once it has
  started training; then the original command again (must say "already done", not hang on a
  stale lock).

Per case: the command (shortened: RUN, CAP = the case's copies, T = its folder, B = the shared
fixture, "…" = the tiny training options), exit code, a Python traceback in stdout/stderr, the
message (one line starting with "error:"?), seconds, data lost (a file of the case folder that
existed before the command changed or disappeared; hidden *.lock files, *.partial folders and
the files a case broke on purpose, with their artefact folder, are not compared), new
*.partial folders and, after a refusal, other new files or folders ("debris": a failed check
must create nothing). Prints a markdown table, a summary per stage and overall; with --out it
also writes DIR/faults.md. Needs root for the mount-based families (skipped otherwise).
"""

from __future__ import annotations

import argparse
import hashlib
import os
import shutil
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import numpy as np

SINE = str(Path(sys.executable).with_name("sine"))
TRACEBACK = "Traceback (most recent call last)"
QUICK_SECONDS = 5.0  # goal for a refusal that needs no training
TIMEOUT = 120  # seconds per command; a command that runs longer counts as hung

# the tiny options of tests/feature_run_helpers.py (TINY_FIT, TINY_FEATURES, TINY_GEOMETRY_EDIT)
# plus a small colour-detail grid (the default one makes checkpoint.pt 68 MB)
FIT = (
    "--iterations 40 --batch-rays 384 --log2-table 12 --levels 8 --max-resolution 128 "
    "--band-samples 8 --density-hidden 128 --coarse-samples 2 --previews 0 "
    "--checkpoint-every 1000 --detail-steps 10 --detail-batch-rays 256 --detail-log2-table 12 "
    "--detail-levels 4 --threads 1 --quiet"
).split()
FEATURES = (
    "--iterations 60 --batch-rays 512 --lr-grid 0.1 --lr-mlp 0.02 --log2-table 12 --levels 8 "
    "--max-resolution 128 --previews 1 --log-every 10 --checkpoint-every 1000 --threads 1 --quiet"
).split()
EDIT = (
    "--iterations 30 --batch-rays 256 --prior-points 300 --cycle-points 200 --smooth-points 200 "
    "--anchor-points 200 --previews 0 --threads 1 --log-every 1 --rebuild-every 25 "
    "--warmup-steps 5 --no-gate --band-width 0.05 --quiet"
).split()
SYNTH = "--procedural toycar --views 8 --width 64 --height 64 --quiet".split()
RENDER = "--orbit 2 --threads 1 --quiet".split()
# the finished edit of the fixture, exactly as it was made ({run} is the case's copy)
EDIT_BASE = ["edit", "{run}", "--target", "{target}", "--view", "0", "--name", "base", *EDIT]
FIXTURE_VERSION = "1 " + " ".join(FIT + FEATURES + EDIT + SYNTH)


# --- the catalogue ---------------------------------------------------------------------------


@dataclass(frozen=True)
class Case:
    """One bad input or fault. `argv` (and `cwd`, `follow_up`) may name {run}, {cap} (the case's
    copies of the fitted run and of the capture), {dir} (the case's folder), {base} (the shared
    fixture) and {target} (the fixture's editing target, an absolute path)."""

    stage: str
    name: str
    argv: tuple[str, ...]
    prep: tuple[tuple, ...] = ()  # (action, path under {dir}, *args): see PREP
    expect: str = "refuse"  # refuse | ok | either
    family: str = "plain"  # plain | readonly | diskfull | concurrent | sigint | sigkill
    where: str = ""  # readonly: the path mounted read-only; diskfull: "run" or the tmpfs folder
    cwd: str = "{dir}"
    says: tuple[str, ...] = ()  # words the output must contain ("a|b": either)
    slow: bool = False  # fails only after training: not held to the 5 s goal
    follow_up: tuple[str, ...] = ()  # interrupt: the command run after the interrupted one


def case(stage, name, argv, **kw) -> Case:
    """A Case with tuples for the list arguments (keeps the table below short)."""
    kw = {k: tuple(v) if isinstance(v, list) else v for k, v in kw.items()}
    return Case(stage, name, tuple(argv), **kw)


FIT_RUN = ["fit", "{run}", *FIT]
FIT_FORCE = [*FIT_RUN, "--force"]
# a fit that runs long enough to be interrupted, its .partial folder there after 20 steps
FIT_LONG = [*FIT_FORCE, "--iterations", "20000", "--checkpoint-every", "20"]
FEAT_RUN = ["features", "{run}", *FEATURES]
MASKS = ["masks", "{run}", "--view", "0", "--out", "{dir}/masks", "--threads", "1", "--quiet"]
SNAP = ["snapshot", "{run}", "--out", "{dir}/snap.png", "--threads", "1"]
RECOLOR = ["target", "{run}", "--view", "0", "--out", "{dir}/t.png", "--recolor", "--hue", "90"]
EDIT_NEW = ["edit", "{run}", "--view", "0", "--name", "new", *EDIT]
RENDER_RUN = ["render", "{run}", "--out", "{dir}/out", *RENDER]
EXPORT = ["export", "{run}", "--device", "cpu"]
REBUILD_FIT = ("sine fit", "--force")
REBUILD_FEATURES = ("sine features", "--force")
REBUILD_EDIT = ("sine edit", "--force")
CORRUPT_TEMPLATE = (("garbage", "run/template/field.pt"),)
TRUNC_TEMPLATE = (("truncate", "run/template/field.pt"),)
TRUNC_CAMERAS = (("truncate", "run/cameras.json"),)
TRUNC_PROXY = (("truncate", "run/proxy_mesh.ply"),)
TRUNC_FEATURES = (("truncate", "run/features/field.pt"),)
TRUNC_EDIT = (("truncate", "run/edits/base/edit_field.pt"),)
NEW_RUN = ["--out", "{dir}/new"]

# fmt: off
CASES: list[Case] = [
    # capture: synth / ingest / recon
    case("capture", "ingest: capture missing", ["ingest", "{dir}/nowhere", *NEW_RUN]),
    case("capture", "ingest: --out is a file", ["ingest", "{cap}", "--out", "{dir}/notes.txt"],
         prep=[("text", "notes.txt")]),
    case("capture", "ingest: --out is the capture", ["ingest", "{cap}", "--out", "{cap}"],
         expect="either"),
    case("capture", "ingest: text file as .png", ["ingest", "{cap}", *NEW_RUN],
         prep=[("image", "capture/images/r_003.png", "text")]),
    case("capture", "ingest: truncated PNG", ["ingest", "{cap}", *NEW_RUN],
         prep=[("image", "capture/images/r_003.png", "truncated")]),
    case("capture", "ingest: 0-byte image", ["ingest", "{cap}", *NEW_RUN],
         prep=[("image", "capture/images/r_003.png", "empty")]),
    case("capture", "ingest: --width 0", ["ingest", "{cap}", *NEW_RUN, "--width", "0"]),
    case("capture", "ingest: other capture into fitted run", ["ingest", "{dir}/seven", "--out",
         "{run}"], prep=[("views", "seven", "{cap}", 7)]),
    case("capture", "recon: 2 views", ["recon", "{dir}/two", *NEW_RUN], prep=[("views", "two", "{cap}", 2)]),
    case("capture", "recon: empty folder", ["recon", "{dir}/empty", *NEW_RUN],
         prep=[("mkdir", "empty")]),
    case("capture", "synth: --views 2", ["synth", "--out", "{dir}/s", *SYNTH, "--views", "2"]),
    # fit
    case("fit", "run dir missing", ["fit", "{dir}/nowhere", *FIT]),
    case("fit", "run is a file", ["fit", "{dir}/notes.txt", *FIT], prep=[("text", "notes.txt")]),
    case("fit", "capture without proxy mesh", ["fit", "{cap}", *FIT], says=["sine recon"]),
    case("fit", "--iterations -1", [*FIT_FORCE, "--iterations", "-1"]),
    case("fit", "--batch-rays 0", [*FIT_FORCE, "--batch-rays", "0"]),
    case("fit", "--threads -4", [*FIT_FORCE, "--threads", "-4"]),
    case("fit", "--lr 1e9 diverges", [*FIT_FORCE, "--lr-grid", "1e9", "--lr-mlp", "1e9"],
         says=["nan|inf|diverg"], slow=True),
    case("fit", "corrupt field.pt, fit again", FIT_RUN, prep=CORRUPT_TEMPLATE, expect="either",
         says=REBUILD_FIT, slow=True),
    case("fit", "truncated checkpoint, resume", FIT_RUN, prep=[("interrupted", "run/template")],
         expect="either", slow=True),
    case("fit", "truncated cameras.json", FIT_FORCE, prep=TRUNC_CAMERAS),
    case("fit", "truncated proxy_mesh.ply", FIT_FORCE, prep=TRUNC_PROXY),
    case("fit", "text file as run image", FIT_FORCE, prep=[("image", "run/images/r_003.png",
         "text")]),
    case("fit", "already done", FIT_RUN, expect="ok", says=["already"]),
    case("fit", "read-only run, already done", FIT_RUN, expect="ok", says=["already"],
         family="readonly", where="{run}"),
    case("fit", "read-only run, --force", FIT_FORCE, family="readonly", where="{run}"),
    case("fit", "disk full, --force", FIT_FORCE, family="diskfull", where="run", slow=True),
    case("fit", "images folder missing", FIT_FORCE, prep=[("remove", "run/images")]),
    case("fit", "SIGINT during --force", FIT_LONG, family="sigint", where="run/template.partial",
         follow_up=FIT_RUN),
    case("fit", "SIGKILL during --force", FIT_LONG, family="sigkill",
         where="run/template.partial", follow_up=FIT_RUN),
    # features
    case("features", "no template", FEAT_RUN, prep=[("remove", "run/template")],
         says=["sine fit"]),
    case("features", "corrupt template field.pt", [*FEAT_RUN, "--force"], prep=CORRUPT_TEMPLATE,
         says=REBUILD_FIT),
    case("features", "truncated features field.pt", FEAT_RUN, prep=TRUNC_FEATURES,
         expect="either", says=REBUILD_FEATURES, slow=True),
    # masks
    case("masks", "region missing", [*MASKS, "--region", "{dir}/nowhere.png"]),
    case("masks", "all-black region", [*MASKS, "--region", "{dir}/black.png"],
         prep=[("image", "black.png", "black")]),
    case("masks", "region of the wrong size", [*MASKS, "--region", "{dir}/small.png"],
         prep=[("image", "small.png", "small")]),
    case("masks", "--view 99", [*MASKS[:2], "--view", "99", *MASKS[4:], "--region",
         "{dir}/white.png"], prep=[("image", "white.png", "white")]),
    case("masks", "truncated features field.pt", [*MASKS, "--region", "{dir}/white.png"],
         prep=[*TRUNC_FEATURES, ("image", "white.png", "white")], says=REBUILD_FEATURES),
    case("masks", "read-only run", [*MASKS, "--region", "{dir}/top.png"], expect="ok",
         prep=[("image", "top.png", "top")], family="readonly", where="{run}"),
    case("masks", "--out is a file", [*MASKS[:4], "--out", "{dir}/notes.txt", "--region",
         "{dir}/white.png"], prep=[("text", "notes.txt"), ("image", "white.png", "white")]),
    # snapshot / target
    case("target", "snapshot --view 99", [*SNAP, "--view", "99"]),
    case("target", "snapshot --view -1", [*SNAP, "--view", "-1"]),
    case("target", "snapshot --out is a folder", ["snapshot", "{run}", "--view", "0", "--out",
         "{dir}/afolder"], prep=[("mkdir", "afolder")]),
    case("target", "snapshot, corrupt field.pt", [*SNAP, "--view", "0"], prep=CORRUPT_TEMPLATE,
         says=REBUILD_FIT),
    case("target", "snapshot --out RUN/images/r_000.png", ["snapshot", "{run}", "--view", "1",
         "--out", "{run}/images/r_000.png", "--threads", "1"]),
    case("target", "two operations", [*RECOLOR, "--region", "{dir}/white.png", "--stretch-axis",
         "y", "--factor", "1.2"], prep=[("image", "white.png", "white")]),
    case("target", "--recolor, all-black region", [*RECOLOR, "--region", "{dir}/black.png"],
         prep=[("image", "black.png", "black")]),
    case("target", "--recolor, region missing", [*RECOLOR, "--region", "{dir}/nowhere.png"]),
    case("target", "--warp 'abc'", ["target", "{run}", "--view", "0", "--out", "{dir}/t.png",
         "--warp", "abc"]),
    case("target", "--factor -1", ["target", "{run}", "--view", "0", "--out", "{dir}/t.png",
         "--stretch-axis", "y", "--factor", "-1"]),
    # edit
    case("edit", "target missing", [*EDIT_NEW, "--target", "{dir}/nowhere.png"]),
    case("edit", "text file as target", [*EDIT_NEW, "--target", "{dir}/bad.png"],
         prep=[("image", "bad.png", "text")]),
    case("edit", "truncated PNG target", [*EDIT_NEW, "--target", "{dir}/bad.png"],
         prep=[("image", "bad.png", "truncated")]),
    case("edit", "0-byte target", [*EDIT_NEW, "--target", "{dir}/bad.png"],
         prep=[("image", "bad.png", "empty")]),
    case("edit", "target at half size (same aspect)", [*EDIT_NEW, "--target", "{dir}/bad.png"],
         prep=[("image", "bad.png", "half", "{target}")], expect="either", slow=True),
    case("edit", "target of the wrong aspect", [*EDIT_NEW, "--target", "{dir}/bad.png"],
         prep=[("image", "bad.png", "aspect")]),
    case("edit", "fully transparent target", [*EDIT_NEW, "--target", "{dir}/bad.png"],
         prep=[("image", "bad.png", "transparent")]),
    case("edit", "--view 99", ["edit", "{run}", "--target", "{target}", "--view", "99", "--name",
         "new", *EDIT]),
    case("edit", "all-black --region", [*EDIT_NEW, "--target", "{target}", "--region",
         "{dir}/black.png"], prep=[("image", "black.png", "black")]),
    case("edit", "--region missing", [*EDIT_NEW, "--target", "{target}", "--region",
         "{dir}/nowhere.png"]),
    case("edit", "--iterations -1", [*EDIT_NEW, "--target", "{target}", "--iterations", "-1"]),
    case("edit", "--lr-deform 1e9 diverges", [*EDIT_NEW, "--target", "{target}", "--lr-deform",
         "1e9"], says=["nan|inf|diverg"], slow=True),
    case("edit", "--target with --reference", [*EDIT_NEW, "--mode", "texture", "--target",
         "{target}", "--reference", "{target}", "--iterations", "3"]),
    case("edit", "hybrid: --target and --target-geometry", [*EDIT_NEW, "--mode", "hybrid",
         "--target", "{target}", "--target-geometry", "{target}"]),
    case("edit", "--name ../escape", ["edit", "{run}", "--target", "{target}", "--view", "0",
         "--name", "../escape", *EDIT]),
    case("edit", "corrupt template field.pt", [*EDIT_NEW, "--target", "{target}"],
         prep=CORRUPT_TEMPLATE, says=REBUILD_FIT),
    case("edit", "truncated template field.pt", [*EDIT_NEW, "--target", "{target}"],
         prep=TRUNC_TEMPLATE, says=REBUILD_FIT),
    case("edit", "truncated cameras.json", [*EDIT_NEW, "--target", "{target}"],
         prep=TRUNC_CAMERAS),
    case("edit", "truncated proxy_mesh.ply", [*EDIT_NEW, "--target", "{target}"],
         prep=TRUNC_PROXY),
    case("edit", "truncated edit_field.pt, edit again", EDIT_BASE, prep=TRUNC_EDIT,
         expect="either", says=REBUILD_EDIT, slow=True),
    case("edit", "truncated checkpoint, resume", EDIT_BASE, prep=[("interrupted",
         "run/edits/base")], expect="either", slow=True),
    case("edit", "already done", EDIT_BASE, expect="ok", says=["already"]),
    case("edit", "already done, relative target path", [*EDIT_BASE[:3], "target.png",
         *EDIT_BASE[4:]], cwd="{base}", expect="ok", says=["already"]),
    case("edit", "read-only run", [*EDIT_NEW, "--target", "{target}"], family="readonly",
         where="{run}"),
    case("edit", "disk full", [*EDIT_NEW, "--target", "{target}"], family="diskfull",
         where="run", slow=True),
    case("edit", "two processes, one name", [*EDIT_NEW, "--target", "{target}"], expect="either",
         family="concurrent", slow=True),
    case("edit", "SIGINT during --force", [*EDIT_BASE, "--force", "--iterations", "5000"],
         family="sigint", where="run/edits/base.partial", follow_up=EDIT_BASE),
    case("edit", "SIGKILL during --force", [*EDIT_BASE, "--force", "--iterations", "5000"],
         family="sigkill", where="run/edits/base.partial", follow_up=EDIT_BASE),
    # render / export / eval / view
    case("output", "render: run missing", ["render", "{dir}/nowhere", "--out", "{dir}/out",
         *RENDER]),
    case("output", "render: --edit missing", [*RENDER_RUN, "--edit", "nope"]),
    case("output", "render: --out is a file", ["render", "{run}", "--out", "{dir}/notes.txt",
         *RENDER], prep=[("text", "notes.txt")]),
    case("output", "render: read-only --out", ["render", "{run}", "--out", "{dir}/ro", *RENDER],
         prep=[("mkdir", "ro")], family="readonly", where="{dir}/ro"),
    case("output", "render: disk full", ["render", "{run}", "--out", "{dir}/full/out", *RENDER],
         family="diskfull", where="full"),
    case("output", "render: read-only run", RENDER_RUN, expect="ok", family="readonly",
         where="{run}"),
    case("output", "render: read-only run, --edit", [*RENDER_RUN, "--edit", "base"],
         expect="ok", family="readonly", where="{run}"),
    case("output", "render: truncated field.pt", RENDER_RUN, prep=TRUNC_TEMPLATE,
         says=REBUILD_FIT),
    case("output", "render: truncated edit_field.pt", [*RENDER_RUN, "--edit", "base"],
         prep=TRUNC_EDIT, says=REBUILD_EDIT),
    case("output", "render: truncated cameras.json", RENDER_RUN, prep=TRUNC_CAMERAS),
    case("output", "render: --strength 5", [*RENDER_RUN, "--edit", "base", "--strength", "5"]),
    case("output", "render: --orbit with --views", [*RENDER_RUN, "--views", "test"]),
    case("output", "render: --chunk 0", [*RENDER_RUN, "--chunk", "0"]),
    case("output", "render: --camera-path corrupt", [*RENDER_RUN[:4], "--camera-path",
         "{dir}/notes.txt", "--quiet"], prep=[("text", "notes.txt")]),
    case("output", "render: --features with --edit", [*RENDER_RUN, "--edit", "base",
         "--features"]),
    case("output", "export: --out .xyz", [*EXPORT, "--out", "{dir}/mesh.xyz"]),
    case("output", "export: read-only --out", [*EXPORT, "--out", "{dir}/ro/mesh.ply"],
         prep=[("mkdir", "ro")], family="readonly", where="{dir}/ro"),
    case("output", "export: --out is a folder", [*EXPORT, "--out", "{dir}/afolder.ply"],
         prep=[("mkdir", "afolder.ply")]),
    case("output", "export: truncated proxy_mesh.ply", [*EXPORT, "--out", "{dir}/m.ply"],
         prep=TRUNC_PROXY),
    case("output", "export: --out RUN/proxy_mesh.ply", [*EXPORT, "--out",
         "{run}/proxy_mesh.ply"]),
    case("output", "export: truncated edit_field.pt", [*EXPORT, "--out", "{dir}/m.ply",
         "--edit", "base"], prep=TRUNC_EDIT, says=REBUILD_EDIT),
    case("output", "eval: --gt missing", ["eval", "{run}", "--gt", "{dir}/nowhere", "--quiet"]),
    case("output", "view: no display", ["view", "{run}"]),
]
# fmt: on


# --- preparing a case's files ----------------------------------------------------------------


def write_image(path: Path, kind: str, source: str = "") -> None:
    """A bad or special image at `path`: text (a text file named .png), truncated (the first half
    of a real PNG), empty (0 bytes), black / white / top (a 64 x 64 region
    painting: nothing, everything, the top half), small (32 x 32
    white), aspect (64 x 48, the run's width but not its aspect), transparent (RGBA, alpha 0) or
    half (the image `source` at half its size: the run's aspect, not its size)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    w, h = 64, 64
    if kind == "half":
        image = cv2.imread(source, cv2.IMREAD_UNCHANGED)
        cv2.imwrite(str(path), cv2.resize(image, (w // 2, h // 2), interpolation=cv2.INTER_AREA))
    elif kind == "text":
        path.write_text("this is not an image\n")
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":
        _, data = cv2.imencode(
            ".png", np.random.default_rng(0).integers(0, 255, (h, w, 3), np.uint8)
        )
        path.write_bytes(data.tobytes()[: len(data) // 2])
    elif kind in ("black", "white"):
        cv2.imwrite(str(path), np.full((h, w), 255 if kind == "white" else 0, np.uint8))
    elif kind == "top":
        image = np.zeros((h, w), np.uint8)
        image[: h // 2] = 255
        cv2.imwrite(str(path), image)
    elif kind == "small":
        cv2.imwrite(str(path), np.full((32, 32, 3), 255, np.uint8))
    elif kind == "aspect":
        cv2.imwrite(str(path), np.full((48, 64, 3), 128, np.uint8))
    elif kind == "transparent":
        cv2.imwrite(str(path), np.zeros((h, w, 4), np.uint8))
    else:
        raise ValueError(kind)


def keep_views(cap: Path, out: Path, count: int) -> None:
    """A plain folder of the first `count` images of the capture (no poses, no masks)."""
    out.mkdir(parents=True)
    for image in sorted((cap / "images").glob("*.png"))[:count]:
        shutil.copy(image, out / image.name)


def as_interrupted(artefact: Path) -> None:
    """Turn a finished artefact folder into an interrupted one with a broken checkpoint: renamed
    to NAME.partial, its final files dropped, checkpoint.pt cut in half."""
    partial = artefact.with_name(artefact.name + ".partial")
    artefact.rename(partial)
    for name in ("field.pt", "edit_field.pt", "metrics.json"):
        (partial / name).unlink(missing_ok=True)
    truncate(partial / "checkpoint.pt")


def truncate(path: Path) -> None:
    """Keep the first half of the file's bytes (a write cut short)."""
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])


PREP = {
    "text": lambda p: p.write_text("notes\n"),
    "garbage": lambda p: p.write_text("not a torch file\n"),
    "truncate": truncate,
    "remove": lambda p: shutil.rmtree(p) if p.is_dir() else p.unlink(),
    "mkdir": lambda p: p.mkdir(parents=True),
    "image": write_image,
    "views": lambda p, cap, n: keep_views(Path(cap), p, n),
    "interrupted": as_interrupted,
}


def damaged_scope(rel: str) -> str:
    """What a file broken on purpose lets a command rebuild: its artefact folder (template/,
    features/, edits/NAME/) or the file itself."""
    parts = Path(rel).parts
    if len(parts) > 2 and parts[1] in ("template", "features"):
        return str(Path(*parts[:2]))
    if len(parts) > 3 and parts[1] == "edits":
        return str(Path(*parts[:3]))
    return rel


# --- looking at a folder ---------------------------------------------------------------------


def ignored(rel: Path) -> bool:
    """Hidden lock files and the .partial work folders are not finished artefacts."""
    return any(p.endswith(".partial") for p in rel.parts) or (
        rel.name.startswith(".") and rel.name.endswith(".lock")
    )


def digest_tree(root: Path) -> dict[str, tuple[str, int]]:
    """(sha1, size) of every file under root by relative path, locks and .partial aside."""
    digests = {}
    for path in root.rglob("*"):
        rel = path.relative_to(root)
        if path.is_file() and not path.is_symlink() and not ignored(rel):
            data = path.read_bytes()
            digests[str(rel)] = (hashlib.sha1(data).hexdigest(), len(data))
    return digests


def lost_files(root: Path, before: dict[str, tuple[str, int]], spared: list[str]) -> list[str]:
    """Files of `before` that changed or disappeared, except under `spared` and except files
    that only grew (their old bytes a prefix of the new: config.yaml, a log of the stages)."""
    lost = []
    for rel, (digest, size) in before.items():
        path = root / rel
        if any(rel == s or rel.startswith(s + "/") for s in spared):
            continue
        if not path.is_file():
            lost.append(rel)
        elif hashlib.sha1(path.read_bytes()[:size]).hexdigest() != digest:
            lost.append(rel)
    return sorted(lost)


def list_tree(root: Path) -> tuple[set[str], set[str]]:
    """(.partial folders, other files and folders) under root, as relative paths."""
    partials, others = set(), set()
    for path in root.rglob("*"):
        rel = path.relative_to(root)
        if path.is_dir() and path.name.endswith(".partial"):
            partials.add(str(rel))
        elif not ignored(rel):
            others.add(str(rel))
    return partials, others


# --- running commands ------------------------------------------------------------------------


@dataclass
class Proc:
    """One finished `sine` process."""

    argv: list[str]
    code: int | str  # exit code, or "hung" after TIMEOUT
    out: str
    err: str
    seconds: float


def env() -> dict[str, str]:
    """The commands' environment: one thread everywhere (a 2-core machine shared with others)."""
    return {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1"}


def start(argv: list[str], cwd: Path) -> tuple[subprocess.Popen, float]:
    """Start a command in its own process group (so that a timeout or signal reaches it all)."""
    proc = subprocess.Popen(
        argv,
        cwd=cwd,
        env=env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        start_new_session=True,
        # Ctrl-C interrupts it as in a terminal, even when the bench itself was started in
        # the background (where the shell hands its children SIGINT ignored)
        preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL),
    )
    return proc, time.perf_counter()


def finish(proc: subprocess.Popen, t0: float, timeout: float = TIMEOUT) -> Proc:
    """Wait for a started command; kill its group and say "hung" after `timeout` seconds."""
    try:
        out, err = proc.communicate(timeout=timeout)
        code: int | str = proc.returncode
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        out, err = proc.communicate()
        code = "hung"
    except BaseException:  # the bench itself interrupted: take the command down with it
        os.killpg(proc.pid, signal.SIGKILL)
        raise
    return Proc(list(proc.args), code, out, err, time.perf_counter() - t0)


def visible_lines(text: str) -> list[str]:
    """The non-empty lines a terminal shows: of each line, what follows its last carriage
    return (a progress bar that erases itself leaves nothing)."""
    lines = (line.split("\r")[-1].strip() for line in text.split("\n"))
    return [line for line in lines if line]


def first_line(proc: Proc) -> str:
    """The first visible line of stderr, else of stdout ("(none)" when both are empty)."""
    lines = visible_lines(proc.err) or visible_lines(proc.out)
    return lines[0] if lines else "(none)"


def run(argv: list[str], cwd: Path, timeout: float = TIMEOUT) -> Proc:
    """Run a command to its end."""
    return finish(*start(argv, cwd), timeout=timeout)


def sine(argv: list[str], cwd: Path, what: str) -> None:
    """Run a fixture-building command; stop the bench if it fails."""
    result = run([SINE, *argv], cwd, timeout=600)
    if result.code != 0:
        sys.exit(f"fixture: {what} failed ({result.code}):\n{result.err[-2000:]}")


def can_mount() -> bool:
    """Whether this process may make mount namespaces and tmpfs mounts (root in most boxes)."""
    with tempfile.TemporaryDirectory() as tmp:
        probe = ["unshare", "-m", "sh", "-c", f"mount -t tmpfs -o size=16k tmpfs {tmp}"]
        try:
            return subprocess.run(probe, capture_output=True).returncode == 0
        except FileNotFoundError:
            return False


# --- the fixture -----------------------------------------------------------------------------


def build_fixture(base: Path) -> None:
    """base/capture (`sine synth`), base/run (the capture with the ground-truth mesh as proxy,
    fitted, with features and the finished edit "base") and base/target.png; reused when
    base/READY names the same options."""
    ready = base / "READY"
    if ready.is_file() and ready.read_text() == FIXTURE_VERSION:
        print(f"fixture: reusing {base}", flush=True)
        return
    t0 = time.perf_counter()
    shutil.rmtree(base, ignore_errors=True)
    base.mkdir(parents=True)
    sine(["synth", "--out", "capture", *SYNTH], base, "synth")
    shutil.copytree(base / "capture", base / "run")
    shutil.copy(base / "run" / "mesh.ply", base / "run" / "proxy_mesh.ply")
    sine(["fit", "run", *FIT], base, "fit")
    sine(["features", "run", *FEATURES], base, "features")
    target = ["--view", "0", "--stretch-axis", "y", "--factor", "1.3", "--threads", "1"]
    sine(["target", "run", "--out", str(base / "target.png"), *target], base, "target")
    edit = [a.format(run=base / "run", target=base / "target.png") for a in EDIT_BASE]
    sine(edit, base, "edit")
    ready.write_text(FIXTURE_VERSION)
    print(f"fixture: built {base} in {time.perf_counter() - t0:.0f} s", flush=True)


# --- one case --------------------------------------------------------------------------------


@dataclass
class Result:
    """What one case did and what is wrong with it."""

    case: Case
    command: str
    code: str
    seconds: float
    number: int = 0  # the case's place in CASES (its folder DIR/cases/NN)
    traceback: bool = False
    message: str = ""  # the first line of stderr (or of stdout when stderr is empty)
    last_line: str = ""  # the last line of stderr (a traceback's exception)
    one_line: bool | None = None  # refusals: one line starting with "error:"
    lost: list[str] = field(default_factory=list)
    partials: list[str] = field(default_factory=list)
    debris: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    says_ok: bool = True  # the output holds the words of Case.says
    procs: list[Proc] = field(default_factory=list)

    @property
    def interrupted(self) -> bool:
        """A case that stops its command on purpose."""
        return self.case.family in ("sigint", "sigkill")

    @property
    def refused(self) -> bool:
        """Every process of the case said no (not interrupted on purpose, not hung)."""
        codes = [p.code for p in self.procs]
        return bool(codes) and not self.interrupted and all(c not in (0, "hung") for c in codes)


class Bench:
    """Runs cases on copies of the fixture in `cases`."""

    def __init__(self, base: Path, cases: Path, keep: bool, mounts: bool):
        self.base, self.cases, self.keep, self.mounts = base, cases, keep, mounts

    def paths(self, folder: Path, run: Path) -> dict[str, str]:
        """The placeholders of a case's argv."""
        return {
            "run": str(run),
            "cap": str(folder / "capture"),
            "dir": str(folder),
            "base": str(self.base),
            "target": str(self.base / "target.png"),
        }

    def shorten(self, argv: list[str], paths: dict[str, str]) -> str:
        """`sine fit RUN … --force`: the case's paths by name, the tiny options as …"""
        text = " ".join(["sine", *argv])
        for options in (FIT, FEATURES, EDIT, SYNTH, RENDER):
            text = text.replace(" ".join(options), "…")
        for name, short in (
            ("run", "RUN"),
            ("cap", "CAP"),
            ("target", "B/target.png"),
            ("dir", "T"),
            ("base", "B"),
        ):
            text = text.replace(paths[name], short)
        return text if len(text) <= 100 else text[:99] + "…"

    def run_case(self, number: int, c: Case) -> Result:
        """Copy the fixture, break what the case breaks, run it, compare the folder."""
        if c.family in ("readonly", "diskfull") and not self.mounts:
            return Result(c, "", "skip", 0.0, number, problems=["skipped: cannot mount"])
        folder = self.cases / f"{number:02d}"
        shutil.rmtree(folder, ignore_errors=True)
        folder.mkdir(parents=True)
        with ExitStack() as stack:
            run_dir = self.place_run(folder, c, stack)
            shutil.copytree(self.base / "capture", folder / "capture")
            paths = self.paths(folder, run_dir)
            damaged = []
            for action, rel, *args in c.prep:
                args = [a.format(**paths) if isinstance(a, str) else a for a in args]
                PREP[action](folder / rel, *args)
                if rel.startswith(("run/", "capture/")):
                    damaged.append(damaged_scope(rel))
            before = digest_tree(folder)
            partials_before, others_before = list_tree(folder)
            argv = [a.format(**paths) for a in c.argv]
            procs = self.execute(c, argv, paths, folder)
            result = self.judge(c, argv, paths, procs)
            result.number = number
            partials_after, others_after = list_tree(folder)
            run_rel = str(run_dir.relative_to(folder))
            scopes = [s.replace("run", run_rel, 1) if s.startswith("run") else s for s in damaged]
            result.lost = lost_files(folder, before, scopes)
            result.partials = sorted(partials_after - partials_before)
            result.debris = sorted(others_after - others_before) if result.refused else []
            self.extra_checks(c, folder, run_dir, result)
        if not self.keep:
            shutil.rmtree(folder, ignore_errors=True)
        self.problems(result)
        return result

    def place_run(self, folder: Path, c: Case, stack: ExitStack) -> Path:
        """The case's copy of the fitted run: folder/run, or on a nearly full tmpfs (diskfull
        "run"); diskfull on a folder mounts a 4 KiB tmpfs there."""
        if c.family == "diskfull":
            mount = folder / "full"
            mount.mkdir()
            size = "64m" if c.where == "run" else "4k"
            subprocess.run(
                ["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(mount)], check=True
            )
            stack.callback(subprocess.run, ["umount", "-l", str(mount)], check=False)
            if c.where == "run":
                shutil.copytree(self.base / "run", mount / "run")
                st = os.statvfs(mount)
                used_kib = (st.f_blocks - st.f_bfree) * st.f_frsize // 1024
                remount = f"remount,size={used_kib + 64}k"
                subprocess.run(["mount", "-o", remount, str(mount)], check=True)
                return mount / "run"
        shutil.copytree(self.base / "run", folder / "run")
        return folder / "run"

    def command(self, c: Case, argv: list[str], paths: dict[str, str]) -> list[str]:
        """The process to start: `sine ARGV`, in a mount namespace where `where` is read-only for
        the readonly family."""
        if c.family != "readonly":
            return [SINE, *argv]
        script = 'mount --bind "$1" "$1" && mount -o remount,bind,ro "$1" && shift && exec "$@"'
        return ["unshare", "-m", "sh", "-c", script, "sh", c.where.format(**paths), SINE, *argv]

    def execute(self, c: Case, argv, paths, folder: Path) -> list[Proc]:
        """Run the case's command(s) by family; the first Proc is the one the row reports."""
        cwd = Path(c.cwd.format(**paths))
        cmd = self.command(c, argv, paths)
        if c.family == "concurrent":
            started = [start(cmd, cwd), start(cmd, cwd)]
            return [finish(*s) for s in started]
        if c.family in ("sigint", "sigkill"):
            proc, t0 = start(cmd, cwd)
            deadline = time.perf_counter() + 60
            while not (folder / c.where).exists() and proc.poll() is None:
                if time.perf_counter() > deadline:
                    break
                time.sleep(0.1)
            time.sleep(1.5)  # into the training loop
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGINT if c.family == "sigint" else signal.SIGKILL)
            first = finish(proc, t0, timeout=60)
            follow = [a.format(**paths) for a in c.follow_up]
            return [first, run([SINE, *follow], cwd)]
        return [run(cmd, cwd, timeout=300 if c.slow else TIMEOUT)]

    def judge(self, c: Case, argv: list[str], paths, procs: list[Proc]) -> Result:
        """Exit code(s), traceback and message of the case's processes. Concurrent: both codes
        (a/b); interrupted: the interrupted command's code, then its re-run's."""
        first = procs[0]
        joiner = " then " if c.family in ("sigint", "sigkill") else "/"
        code = joiner.join(str(p.code) for p in procs)
        result = Result(c, self.shorten(argv, paths), code, max(p.seconds for p in procs))
        result.procs = procs
        result.traceback = any(TRACEBACK in p.out + p.err for p in procs)
        said = " ".join(p.out + p.err for p in procs).lower()
        result.says_ok = all(any(alt.lower() in said for alt in word.split("|")) for word in c.says)
        if result.interrupted:
            result.seconds = first.seconds
            result.message = f"{first_line(first)} ‖ then: {first_line(procs[1])}"
            return result
        failing = [p for p in procs if p.code not in (0, "hung")]
        result.message = first_line(failing[0] if failing else first)
        result.last_line = (visible_lines((failing or procs)[0].err) or [""])[-1]
        if failing:
            result.one_line = all(self.one_line(p.err) for p in failing)
        usage = [p for p in failing if p.err.lstrip().startswith("usage:")]
        if usage:  # argparse's own usage + error lines
            result.one_line = None
            result.message = "argparse: " + visible_lines(usage[0].err)[-1]
        return result

    @staticmethod
    def one_line(err: str) -> bool:
        """One visible line that starts with "error:"."""
        lines = visible_lines(err)
        return len(lines) == 1 and lines[0].startswith("error:")

    def extra_checks(self, c: Case, folder: Path, run_dir: Path, result: Result) -> None:
        """Family checks: both concurrent edits made one complete edit; an interrupted command's
        follow-up did not hang or fail."""
        if c.family == "concurrent":
            want = {p.name for p in (self.base / "run" / "edits" / "base").iterdir()}
            edit = run_dir / "edits" / "new"
            have = {p.name for p in edit.iterdir()} if edit.is_dir() else set()
            if not want <= have:
                result.problems.append(f"edits/new incomplete ({len(have)}/{len(want)} files)")
        if result.interrupted:
            follow = result.procs[1]
            if follow.code != 0:
                result.problems.append(f"re-run after the interrupt: exit {follow.code}")
            elif "already" not in (follow.out + follow.err).lower():
                result.problems.append("re-run after the interrupt trained again")

    def problems(self, r: Result) -> None:
        """Everything that misses a goal, in words."""
        c, p = r.case, r.problems
        if r.code == "skip":
            return
        if "hung" in r.code:
            p.append(f"hung > {TIMEOUT} s")
        if r.traceback:
            p.append("traceback")
        if r.lost:
            p.append(f"data lost ({len(r.lost)} files)")
        if r.partials and not r.interrupted:
            p.append(f"{len(r.partials)} .partial left")
        if r.debris:
            p.append(f"created {len(r.debris)} paths")
        if c.expect == "refuse" and not r.interrupted and r.code == "0":
            p.append("accepted (should refuse)")
        if c.expect == "ok" and r.code != "0":
            p.append("failed (should succeed)")
        if r.one_line is False:
            p.append("message not one 'error:' line" if r.message else "no message")
        if c.says and not r.says_ok and (r.refused or c.expect == "ok"):
            p.append("message lacks " + " + ".join(f"'{w}'" for w in c.says))
        if r.refused and not c.slow and r.seconds > QUICK_SECONDS:
            p.append(f"slow refusal ({r.seconds:.1f} s)")


# --- report ----------------------------------------------------------------------------------


def cell(text: str, width: int = 0) -> str:
    """A markdown table cell: pipes escaped, optionally cut to `width` characters."""
    text = text.replace("|", "\\|").replace("\n", " ")
    return text if not width or len(text) <= width else text[: width - 1] + "…"


def report(results: list[Result], wall: float, floor: float) -> str:
    """The markdown table, the per-stage summary and the overall summary (`floor`: seconds of
    `python -c "import torch"` now, the least a refusal after the imports can take)."""
    rows = [
        "| # | stage | case | command | exit | tb | msg | s | lost | .partial | verdict | message |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for r in results:
        msg = {True: "1 line", False: "BAD", None: "-"}[r.one_line]
        if r.one_line is None and r.message.startswith("argparse"):
            msg = "usage"
        verdict = (
            "skip"
            if r.code == "skip"
            else ("FAIL: " + "; ".join(r.problems))
            if (r.problems)
            else "ok"
        )
        rows.append(
            f"| {r.number} | {r.case.stage} | {cell(r.case.name)} | `{cell(r.command)}` | {r.code} | "
            f"{'YES' if r.traceback else '-'} | {msg} | {r.seconds:.1f} | "
            f"{len(r.lost) or '-'} | {len(r.partials) or '-'} | {cell(verdict)} | "
            f"{cell(r.message, 110)} |"
        )
    done = [r for r in results if r.code != "skip"]
    stages = list(dict.fromkeys(r.case.stage for r in results))
    rows += [
        "",
        "| stage | cases | pass | tracebacks | data lost | bad messages | .partial left "
        "| created paths | max s (refused, quick) |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for stage in stages:
        rs = [r for r in done if r.case.stage == stage]
        quick = [r.seconds for r in rs if r.refused and not r.case.slow]
        rows.append(
            f"| {stage} | {len(rs)} | {sum(not r.problems for r in rs)} | "
            f"{sum(r.traceback for r in rs)} | {sum(bool(r.lost) for r in rs)} | "
            f"{sum(r.one_line is False for r in rs)} | "
            f"{sum(bool(r.partials) for r in rs if not r.interrupted)} | "
            f"{sum(bool(r.debris) for r in rs)} | {max(quick, default=0):.1f} |"
        )
    quick = [r.seconds for r in done if r.refused and not r.case.slow]
    skipped = [r.case.name for r in results if r.code == "skip"]
    failed = [r for r in done if r.problems]
    lines = [
        "",
        f"- cases tried: {len(done)} (skipped: {len(skipped)}{': ' if skipped else ''}"
        f"{', '.join(skipped)}); passing every goal: {len(done) - len(failed)}",
        f"- tracebacks (goal 0): {sum(r.traceback for r in done)}",
        f"- data lost (goal 0): {sum(bool(r.lost) for r in done)}",
        f"- multi-line or missing messages (goal 0): {sum(r.one_line is False for r in done)}"
        f"; argparse usage errors (2 lines, argparse's own format): "
        f"{sum(r.message.startswith('argparse') for r in done)}",
        f"- leftover .partial folders (goal 0): "
        f"{sum(len(r.partials) for r in done if not r.interrupted)}",
        f"- other paths created by refused commands (goal 0): {sum(len(r.debris) for r in done)}",
        f"- refusals accepted instead / expected successes failed: "
        f"{sum(any(s.startswith('accepted') for s in r.problems) for r in done)} / "
        f"{sum(any(s.startswith('failed') for s in r.problems) for r in done)}",
        f"- seconds of a quick refusal (goal < {QUICK_SECONDS:.0f} s): max "
        f"{max(quick, default=0):.1f}, median {statistics.median(quick) if quick else 0:.1f} "
        f"over {len(quick)}; over the goal: {sum(s > QUICK_SECONDS for s in quick)} "
        f"(for scale: `import torch` alone takes {floor:.1f} s here now)",
        f"- wall time: {wall:.0f} s",
    ]
    details = ["", "Failures in detail:", ""]
    slow_only = [r for r in failed if all(p.startswith("slow") for p in r.problems)]
    if slow_only:
        numbers = ", ".join(f"#{r.number} ({r.seconds:.1f} s)" for r in slow_only)
        details.append(f"- only too slow (a refusal over {QUICK_SECONDS:.0f} s): {numbers}")
    for r in failed:
        if any(r is slow for slow in slow_only):
            continue
        details.append(f"- #{r.number} {r.case.stage}: {r.case.name}: {'; '.join(r.problems)}")
        if r.traceback or r.one_line is False:
            details.append(f"  - stderr ends: {cell(r.last_line, 200)}")
        for label, paths in (("lost", r.lost), (".partial", r.partials), ("created", r.debris)):
            if paths:
                more = f" (+{len(paths) - 4} more)" if len(paths) > 4 else ""
                details.append(f"  - {label}: {', '.join(paths[:4])}{more}")
    return "\n".join(rows + lines + (details if failed else []))


def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, help="keep (and reuse) the fixture here, write faults.md")
    ap.add_argument("--keep", action="store_true", help="keep each case's folder (DIR/cases/NN)")
    ap.add_argument("--only", help="run only the cases whose stage or name contains this")
    args = ap.parse_args()
    if not Path(SINE).is_file():
        sys.exit(f"no `sine` next to {sys.executable}: run this with the project's .venv python")
    t0 = time.perf_counter()
    root = args.out.resolve() if args.out else Path(tempfile.mkdtemp(prefix="bench_faults_"))
    try:
        build_fixture(root / "base")
        cases_dir = root / "cases"
        shutil.rmtree(cases_dir, ignore_errors=True)
        mounts = can_mount()
        if not mounts:
            print("note: no mount namespaces / tmpfs here: readonly and diskfull cases skipped")
        bench = Bench(root / "base", cases_dir, args.keep, mounts)
        selected = [
            (i, c)
            for i, c in enumerate(CASES, 1)
            if not args.only or args.only in c.stage or args.only in c.name
        ]
        results = []
        for i, c in selected:
            r = bench.run_case(i, c)
            results.append(r)
            state = "ok" if not r.problems else "; ".join(r.problems)
            print(
                f"[{i:2d}/{len(CASES)}] {c.stage}: {c.name}: exit {r.code}, "
                f"{r.seconds:.1f} s, {state}",
                flush=True,
            )
        if not args.keep:
            shutil.rmtree(cases_dir, ignore_errors=True)
        floor = run([sys.executable, "-c", "import torch"], root).seconds
        text = report(results, time.perf_counter() - t0, floor)
        print()
        print(text)
        if args.out:
            (root / "faults.md").write_text(text + "\n")
    finally:
        if not args.out:
            shutil.rmtree(root, ignore_errors=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
