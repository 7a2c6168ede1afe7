"""kill -9 fault injection for the `sine` stages (used by tests/test_faults.py).

A stage is a `sine` command run as a subprocess in a working folder WORK that holds a copy of
the stage's input run as WORK/run. `reference_run` runs it to the end and times it (T).
`kill_and_rerun` starts the same command on a fresh copy of the input, sends SIGKILL to its
process group at a kill point, then runs the same command again to the end, and compares:

* the re-run exits 0 and leaves no `.partial` folder of the stage;
* the stage's outputs hold the same files as the reference run's (a stray temporary file
  counts) with equal contents (`assert_same_tree`): torch files tensor for tensor, JSON value
  for value, .npy/.npz arrays by value, anything else byte for byte; values under keys that
  hold wall-clock times (`TIMING`) are left out, no two runs take the same time;
* every other file of the protected folders (the run's earlier results, the capture) has the
  digest it had before the kill (`VOLATILE` files aside: the config log and lock files).

Kill points: SIGKILL `after` seconds from the start, or `after` seconds from the moment a file
(a checkpoint) first exists; or the process SIGKILLs itself right after the Nth call of a
function returns (`KILL_AT`: a code point no timing can hit reliably).
"""

from __future__ import annotations

import hashlib
import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
# keys whose values are wall-clock measurements (train_seconds, rays_per_second, ...)
TIMING = re.compile(r"seconds|per_second")
# changed by every stage, whatever happens: the run's config log (each stage appends its
# options with a time stamp) and lock files (they hold the holder's PID and command)
VOLATILE = re.compile(r"(^|/)(config\.yaml|\.[^/]*\.lock)$")


def sine_env() -> dict:
    env = dict(os.environ)
    env["OMP_WAIT_POLICY"] = "PASSIVE"  # sleeping OpenMP threads: a small shared CPU
    env["PYTHONUNBUFFERED"] = "1"
    return env


def sine_command(*args) -> list[str]:
    return [sys.executable, "-m", "sine_cli", *map(str, args)]


# `python -c KILL_AT MODULE:ATTR N ARGS...`: `sine ARGS`, SIGKILLed by itself right after the
# Nth call of MODULE.ATTR (a function, or a method as Class.method) has returned
KILL_AT = """
import importlib, os, signal, sys
target, nth = sys.argv[1], int(sys.argv[2])
module, _, attr = target.partition(":")
owner = importlib.import_module(module)
*path, name = attr.split(".")
for part in path:
    owner = getattr(owner, part)
original, calls = getattr(owner, name), [0]
def wrapper(*args, **kwargs):
    result = original(*args, **kwargs)
    calls[0] += 1
    if calls[0] == nth:
        os.kill(os.getpid(), signal.SIGKILL)
    return result
setattr(owner, name, wrapper)
import sine_cli
sys.exit(sine_cli.main(sys.argv[3:]))
"""


def kill_at_command(target: str, nth: int, *args) -> list[str]:
    return [sys.executable, "-c", KILL_AT, target, str(nth), *map(str, args)]


@dataclass
class Ended:
    returncode: int
    seconds: float  # from the start to the end (or to the kill)
    output: str
    triggered: float | None = None  # when the watched file first existed, from the start


def run_watched(
    command: list,
    log: Path,
    watch: Path | None = None,
    kill: Callable[[float | None], float | None] | None = None,
    timeout: float = 600.0,
) -> Ended:
    """Runs `command` (stdout + stderr into `log`), noting when the file `watch` first exists.
    `kill(triggered)`: seconds from the start at which to SIGKILL its process group (None: not
    yet), asked as long as it runs; `triggered`: when `watch` appeared (None: not yet).
    returncode -9: killed."""
    t0 = time.perf_counter()
    triggered = kill_at = None
    with open(log, "w") as out:
        proc = subprocess.Popen(
            command,
            cwd=REPO,
            env=sine_env(),
            stdout=out,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # its own process group: the kill reaches its children too
        )
        try:
            while proc.poll() is None:
                now = time.perf_counter() - t0
                if triggered is None and watch is not None and watch.exists():
                    triggered = now
                if kill is not None and kill_at is None:
                    kill_at = kill(triggered)
                if kill_at is not None and now >= kill_at:
                    os.killpg(proc.pid, signal.SIGKILL)
                    break
                if now > timeout:
                    raise TimeoutError(f"{command} ran for more than {timeout} s")
                time.sleep(0.005)
        finally:
            if proc.poll() is None:  # killed above, or an error here: no process left behind
                try:
                    os.killpg(proc.pid, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            proc.wait()
    return Ended(proc.returncode, time.perf_counter() - t0, log.read_text(), triggered)


def run_stage(args: list, log: Path, watch: Path | None = None) -> Ended:
    """Runs `sine ARGS` to the end; fails unless it exits 0."""
    done = run_watched(sine_command(*args), log, watch)
    command = " ".join(map(str, args))
    assert done.returncode == 0, f"`sine {command}` exited {done.returncode}:\n{done.output}"
    return done


# ---- digests and comparisons --------------------------------------------------------------
def files_of(root: Path) -> list[str]:
    """Relative paths of the files under `root` (a file: its name), volatile ones left out."""
    root = Path(root)
    if root.is_file():
        return [root.name]
    if not root.is_dir():
        return []
    paths = (p.relative_to(root).as_posix() for p in root.rglob("*") if p.is_file())
    return sorted(p for p in paths if not VOLATILE.search(p))


def tree_digest(root: Path, exclude: tuple[str, ...] = ()) -> dict[str, str]:
    """{relative path: sha256} of the files under `root`, volatile files and the relative paths
    `exclude` (and what lies under them) left out."""
    root = Path(root)
    out = {}
    for rel in files_of(root):
        if not any(rel == e or rel.startswith(e + "/") for e in exclude):
            out[rel] = hashlib.sha256((root / rel).read_bytes()).hexdigest()
    return out


def assert_same_digest(before: dict, after: dict, what: str) -> None:
    changed = sorted(k for k in before.keys() & after.keys() if before[k] != after[k])
    gone = sorted(before.keys() - after.keys())
    new = sorted(after.keys() - before.keys())
    assert not (changed or gone or new), (
        f"{what}: files changed by the killed and re-run stage: changed {changed}, removed "
        f"{gone}, added {new}"
    )


def strip_timing(value):
    """`value` without the entries under TIMING keys; JSON text inside it is parsed."""
    if isinstance(value, dict):
        return {k: strip_timing(v) for k, v in value.items() if not TIMING.search(str(k))}
    if isinstance(value, (list, tuple)):
        return [strip_timing(v) for v in value]
    if isinstance(value, str) and value[:1] in ("[", "{"):
        try:
            return strip_timing(json.loads(value))
        except json.JSONDecodeError:
            return value
    return value


def assert_same_value(a, b, where: str) -> None:
    """Bit-exact equality of nested dicts / lists / tensors / arrays / plain values."""
    import torch

    if isinstance(a, torch.Tensor) or isinstance(b, torch.Tensor):
        assert isinstance(a, torch.Tensor) and isinstance(b, torch.Tensor), where
        assert a.dtype == b.dtype and a.shape == b.shape, (where, a.dtype, b.dtype, a.shape)
        if not torch.equal(a, b):
            if a.is_floating_point():
                diff = (a.double() - b.double()).abs().max().item()
                raise AssertionError(f"{where}: tensors differ (max |difference| {diff:.3g})")
            raise AssertionError(f"{where}: tensors differ")
    elif isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        a, b = np.asarray(a), np.asarray(b)
        assert a.dtype == b.dtype and a.shape == b.shape, (where, a.dtype, b.dtype)
        assert np.array_equal(a, b, equal_nan=a.dtype.kind in "fc"), f"{where}: arrays differ"
    elif isinstance(a, dict):
        assert isinstance(b, dict), where
        assert sorted(map(str, a)) == sorted(map(str, b)), (where, sorted(a), sorted(b))
        for k in a:
            assert_same_value(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), (where, a, b)
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same_value(x, y, f"{where}[{i}]")
    elif isinstance(a, float) and isinstance(b, float) and a != a and b != b:
        pass  # both NaN
    elif isinstance(a, bytes) and isinstance(b, bytes):
        if a != b:
            pairs = enumerate(zip(a, b, strict=False))
            first = next((i for i, (x, y) in pairs if x != y), min(len(a), len(b)))
            raise AssertionError(
                f"{where}: bytes differ ({len(a)} and {len(b)} bytes, from byte {first} on)"
            )
    else:
        assert a == b, f"{where}: {str(a)[:200]!r} != {str(b)[:200]!r}"


def canonical_mesh(path: Path) -> tuple[np.ndarray, np.ndarray]:
    """A triangle mesh's vertices sorted, and its faces re-indexed to that order, each face
    rotated to start at its smallest index (orientation kept) and the faces sorted: equal for
    two files holding the same mesh in other vertex / face orders."""
    import open3d as o3d

    mesh = o3d.io.read_triangle_mesh(str(path))
    v, f = np.asarray(mesh.vertices), np.asarray(mesh.triangles)
    order = np.lexsort(v.T[::-1])
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    f = rank[f]
    if len(f):
        first = f.argmin(axis=1)
        f = np.stack([np.roll(t, -int(i)) for t, i in zip(f, first, strict=True)])
        f = f[np.lexsort(f.T[::-1])]
    return v[order], f


def load_file(path: Path):
    """A file's content as a comparable value (see the module docstring)."""
    suffix = path.suffix.lower()
    if suffix == ".pt":
        import torch

        return strip_timing(torch.load(path, map_location="cpu", weights_only=True))
    if suffix == ".json":
        return strip_timing(json.loads(path.read_text()))
    if suffix == ".npy":
        return np.load(path, allow_pickle=False)
    if suffix == ".npz":
        with np.load(path, allow_pickle=False) as data:
            return {k: data[k] for k in data.files}
    return path.read_bytes()


Comparison = Callable[[Path, Path, str], None]


def assert_same_tree(
    reference: Path, result: Path, what: str, special: dict[str, Comparison] | None = None
) -> None:
    """`result` (a folder or a file) holds the same files as `reference`, no more and no fewer,
    each equal as `load_file` reads it, or as `special[path relative to reference]` compares
    it. Every difference is listed."""
    special = special or {}
    ref_files, new_files = files_of(reference), files_of(result)
    problems = []
    if ref_files != new_files:
        problems.append(
            f"other files than the uninterrupted run's: missing "
            f"{sorted(set(ref_files) - set(new_files))}, extra "
            f"{sorted(set(new_files) - set(ref_files))}"
        )
    for rel in sorted(set(ref_files) & set(new_files)):
        a, b = (reference, result) if Path(reference).is_file() else (reference / rel, result / rel)
        try:
            if rel in special:
                special[rel](a, b, rel)
            else:
                assert_same_value(load_file(a), load_file(b), rel)
        except AssertionError as exc:
            problems.append(str(exc).splitlines()[0][:400])
    assert not problems, f"{what}:\n  " + "\n  ".join(problems)


def complete(reference: Path, result: Path) -> bool:
    """Whether `result` holds every file `reference` does (a stage that had finished)."""
    return set(files_of(reference)) <= set(files_of(result))


# ---- a stage and its kill points ------------------------------------------------------------
@dataclass
class Stage:
    """One stage, `sine ARGS` in a working folder WORK that holds a copy of the run `source`
    as WORK/run (none for `sine recon`, which makes WORK/run).

    `args(work)`: the command's arguments; `outputs`: what the stage writes, relative to WORK
    (each compared with the reference run's); `protected`: folders (relative to WORK, or
    absolute) whose other files must not change; `special`: output -> {path relative to that
    output: comparison} where it is not `assert_same_value`'s bit-exact equality; `partial`:
    the stage's `.partial` folders (relative to WORK), which a finished run must not leave;
    `checkpoint`: its first checkpoint's file (relative to WORK), which checkpoint kill points
    count from."""

    name: str
    source: Path | None
    args: Callable[[Path], list]
    outputs: tuple[str, ...]
    protected: tuple[str, ...] = ("run",)
    special: dict[str, dict[str, Comparison]] = field(default_factory=dict)
    partial: tuple[str, ...] = ()
    checkpoint: str | None = None


@dataclass
class Reference:
    stage: Stage
    work: Path
    seconds: float  # T
    first_checkpoint: float | None  # when the first checkpoint appeared, from the start

    @property
    def run(self) -> Path:
        return self.work / "run"


@dataclass
class KillPoint:
    kind: str  # "start", "checkpoint" (see `kill_and_rerun`) or "at MODULE:ATTR N"
    delay: float
    returncode: int
    seconds: float  # when it was killed (or ended), from the start
    triggered: float | None  # when its first checkpoint appeared, from the start
    left: str  # what the killed run left behind (checkpoint step, files)
    mid_stage: bool  # killed (-9) before the stage's outputs were complete
    rerun_seconds: float = 0.0

    def describe(self, stage: str) -> str:
        if self.kind.startswith("at "):
            target, nth = self.kind[3:].split()
            where = f"kill -9 right after call {nth} of {target} returned ("
        else:
            where = f"kill {self.delay:.2f} s after the {self.kind} ("
            if self.kind == "checkpoint":
                first = "never" if self.triggered is None else f"at {self.triggered:.2f} s"
                where += f"first checkpoint {first}, "
        return (
            f"{stage}: {where}killed at {self.seconds:.2f} s, exit {self.returncode}, "
            f"{'mid-stage' if self.mid_stage else 'had finished'}; left: {self.left}); "
            f"re-run {self.rerun_seconds:.1f} s"
        )


def prepare(stage: Stage, work: Path) -> Path:
    """A fresh working folder with a copy of the stage's input run."""
    if work.exists():
        shutil.rmtree(work)
    work.mkdir(parents=True)
    if stage.source is not None:
        shutil.copytree(stage.source, work / "run", symlinks=True)
    return work


def reference_run(stage: Stage, base: Path) -> Reference:
    """The stage run to the end on a copy of its input, timed."""
    work = prepare(stage, base / f"{stage.name}-reference")
    watch = None if stage.checkpoint is None else work / stage.checkpoint
    done = run_stage(stage.args(work), base / f"{stage.name}-reference.log", watch)
    for rel in stage.outputs:
        assert (work / rel).exists(), f"{stage.name}: the reference run wrote no {rel}"
    return Reference(stage, work, done.seconds, done.triggered)


def _protected_digests(stage: Stage, work: Path) -> dict[str, dict]:
    out = {}
    for folder in stage.protected:
        root = Path(folder) if Path(folder).is_absolute() else work / folder
        exclude = tuple(
            (work / o).relative_to(root).as_posix()
            for o in stage.outputs
            if (work / o).is_relative_to(root) and (work / o) != root
        )
        out[str(root)] = tree_digest(root, exclude)
    return out


def describe_leftovers(stage: Stage, work: Path) -> str:
    """What a killed run left: the step of each `.partial` checkpoint, its temporary files,
    the outputs that exist."""
    from recon.training import read_checkpoint_header

    notes = []
    for rel in stage.partial:
        folder = work / rel
        if not folder.is_dir():
            continue
        header = read_checkpoint_header(folder / "checkpoint.pt")
        stray = sorted(p.name for p in folder.rglob(".*") if p.is_file())
        step = f"checkpoint at step {header['step']}" if header else "no checkpoint"
        notes.append(f"{rel}: {step}" + (f", temporary files {stray}" if stray else ""))
    for rel in stage.outputs:
        if (work / rel).exists():
            notes.append(f"{rel} exists ({len(files_of(work / rel))} files)")
    return "; ".join(notes) or "no output yet"


def kill_and_rerun(
    reference: Reference, base: Path, kind: str, fraction: float, index: int | str
) -> KillPoint:
    """On a fresh copy of the stage's input: SIGKILL at the kill point, then the same command to
    the end; asserts what the module docstring says. Kill points (`kind`):

    "start": `fraction` x T seconds after the start;
    "checkpoint": after the first checkpoint exists, `fraction` of the time the reference run
        took from its first checkpoint to its end, scaled by how much slower or faster this
        run reached its first checkpoint (the machine's load changes);
    "at MODULE:ATTR N": the stage SIGKILLs itself right after the Nth call of that function.
    """
    stage = reference.stage
    work = prepare(stage, base / f"{stage.name}-kill{index}")
    args = stage.args(work)
    before = _protected_digests(stage, work)
    log = base / f"{stage.name}-kill{index}.log"
    watch = None if stage.checkpoint is None else work / stage.checkpoint
    delay = fraction * reference.seconds
    if kind.startswith("at "):
        target, nth = kind[3:].split()
        killed = run_watched(kill_at_command(target, int(nth), *args), log, watch)
    elif kind == "start":
        killed = run_watched(sine_command(*args), log, watch, kill=lambda _: delay)
    else:
        first = reference.first_checkpoint
        assert first is not None, f"{stage.name}: the reference run wrote no {stage.checkpoint}"
        remaining = reference.seconds - first

        def kill(triggered):
            nonlocal delay
            if triggered is None:
                return None
            delay = fraction * remaining * triggered / first
            return triggered + delay

        killed = run_watched(sine_command(*args), log, watch, kill=kill)
    assert killed.returncode in (0, -signal.SIGKILL), (
        f"{stage.name}: the run to be killed failed by itself (exit {killed.returncode}):\n"
        f"{killed.output}"
    )
    left = describe_leftovers(stage, work)
    finished = all(complete(reference.work / o, work / o) for o in stage.outputs) and not any(
        (work / p).exists() for p in stage.partial
    )
    rerun = run_stage(args, base / f"{stage.name}-kill{index}-rerun.log")
    point = KillPoint(
        kind,
        delay,
        killed.returncode,
        killed.seconds,
        killed.triggered,
        left,
        mid_stage=killed.returncode == -signal.SIGKILL and not finished,
        rerun_seconds=rerun.seconds,
    )
    what = point.describe(stage.name)
    for rel in stage.partial:
        assert not (work / rel).exists(), f"{what}: {rel} is left after the re-run"
    for rel in stage.outputs:
        special = stage.special.get(rel, {})
        assert_same_tree(reference.work / rel, work / rel, f"{what}: {rel}", special)
    after = _protected_digests(stage, work)
    for root, digest in before.items():
        assert_same_digest(digest, after[root], f"{what}: {root}")
    shutil.rmtree(work)  # the disk of a CI machine is small too
    return point
