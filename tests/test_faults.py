"""kill -9 in the middle of every long stage, then the same command again: the result is the
uninterrupted run's, and nothing else in the run changed.

One tiny toycar capture (`sine synth`, 8 views of 64 x 64) goes through the stages once, each
as a `sine` subprocess timed to T (the reference chain: recon -> fit -> features -> the three
edit modes; the geometric edit -> render and export). For each stage, on a fresh copy of its
input, the same command is started and SIGKILLed at a kill point, then run again to the end
(tests/fault_helpers.py). Kill points, two or three per stage, two at a time: a seeded random
delay in [0.3 T, 0.85 T] from the start; for the training stages (checkpoints every 5 steps)
one after the first checkpoint appeared, so that the re-run resumes from a checkpoint however
loaded the machine is; for recon and the geometric edit, a code point (the stage kills itself
there) that no delay hits reliably.

The re-run must exit 0 and leave exactly the reference run's files: torch files (fields,
checkpoints, DINO caches) tensor for tensor, JSON (metrics, logs, recon state) value for value
without wall-clock timings, arrays by value, PNGs, PLYs and everything else byte for byte.
The exceptions, each explained where it is made: recon's proxy mesh is compared as a mesh
(`same_mesh`: Open3D writes it in a varying order) and its volume to rounding
(`same_recon_record`), and the texture and hybrid edits' checkpoint.pt without torch's global
RNG state (`same_checkpoint_but_global_rng`). Every other
file of the run (the capture, the earlier stages' results) must be unchanged. pytest -s prints
where each kill point fell and what the killed run had left.
"""

from __future__ import annotations

import random
from concurrent.futures import ThreadPoolExecutor

import numpy as np
import pytest
from fault_helpers import (
    KillPoint,
    Reference,
    Stage,
    assert_same_value,
    canonical_mesh,
    kill_and_rerun,
    load_file,
    reference_run,
    run_stage,
)
from feature_run_helpers import TINY_FEATURES, TINY_FIT, TINY_GEOMETRY_EDIT, TINY_TEXTURE_EDIT

pytestmark = pytest.mark.slow  # the full tier (`make test-all`)

SEED = 20261207
GEO_VIEW, TEX_VIEW = 0, 2  # the car's front (stretched upwards); its side (the body recoloured)
BODY = 1  # the toycar's body label


def flags(options: dict, **changes) -> list[str]:
    """A TINY_* config as `sine` options (its fields are the commands' options)."""
    out = []
    for key, value in {**options, **changes}.items():
        name = "--" + key.replace("_", "-")
        if isinstance(value, bool):
            out.append(name if value else "--no-" + name[2:])
        else:
            out += [name, str(value)]
    return out


# checkpoints every 5 steps: a kill loses little and the re-run resumes from one
FIT = flags(TINY_FIT, checkpoint_every=5, threads=1) + ["--quiet"]
FEATURES = flags(TINY_FEATURES, checkpoint_every=5, threads=1) + ["--quiet"]
GEOMETRY = flags(TINY_GEOMETRY_EDIT, checkpoint_every=5) + ["--quiet"]
TEXTURE = flags(TINY_TEXTURE_EDIT, iterations=8, checkpoint_every=5) + ["--quiet"]
# hybrid: 6 geometric then 6 texture steps (both configs' options; the shared ones once)
HYBRID = flags({**TINY_GEOMETRY_EDIT, **TINY_TEXTURE_EDIT}, iterations=6, checkpoint_every=5)
HYBRID += ["--quiet"]
# four orbit frames of the geometric edit, beside the template's (--compare)
RENDER = ["--edit", "geometry", "--compare", "--orbit", 4, "--threads", 1, "--quiet"]


# ---- comparisons other than bit-exact ---------------------------------------------------------
def same_mesh(a, b, where: str) -> None:
    """The proxy mesh of two recon runs differs in vertex and face order (Open3D's TSDF
    extraction walks a hash map whose order varies from run to run, uninterrupted runs
    included); the mesh itself must be the same: its vertices and faces, exactly, as sets."""
    va, fa = canonical_mesh(a)
    vb, fb = canonical_mesh(b)
    assert va.shape == vb.shape and np.array_equal(va, vb), f"{where}: other vertices"
    assert fa.shape == fb.shape and np.array_equal(fa, fb), f"{where}: other faces"


def same_recon_record(a, b, where: str) -> None:
    """recon_state.json / recon_report.json: exact, but for the proxy's volume, a sum over its
    faces in the order the mesh happens to have (see `same_mesh`): equal to rounding."""
    x, y = load_file(a), load_file(b)
    volumes = []
    for data in (x, y):
        stats = data.get("stages", {}).get("proxy_mesh", data)  # the state, or the report
        volumes.append(stats.pop("proxy_volume"))
    assert volumes[0] == pytest.approx(volumes[1], rel=1e-12, abs=0), f"{where}: {volumes}"
    assert_same_value(x, y, where)


def same_checkpoint_but_global_rng(a, b, where: str) -> None:
    """The finished texture and hybrid edits' checkpoint.pt, bit-exact except torch's global
    RNG state (torch_rng): building the texture steps draws from torch's global generator
    after `Trainer.start` restored it (DINO's modules are initialised at random before their
    weights load), so a resumed run ends with the global generator further on than the
    uninterrupted one. The steps draw from the trainer's own generator only, so every
    parameter, optimiser state and output is still compared bit for bit."""
    x, y = load_file(a), load_file(b)
    for data in (x, y):
        data.pop("torch_rng"), data.pop("cuda_rng", None)
    assert_same_value(x, y, where)


EDIT_CHECKPOINT = {"checkpoint.pt": same_checkpoint_but_global_rng}


# ---- the reference chain ----------------------------------------------------------------------
def synth(base):
    cap = base / "capture"
    args = ["synth", "--procedural", "toycar", "--views", 8, "--width", 64, "--height", 64]
    run_stage([*args, "--out", cap, "--quiet"], base / "synth.log")
    return cap


def make_targets(run, capture, out):
    """Editing targets from the fitted template (made here, as tests/test_edit_*.py make
    theirs): GEO_VIEW with the car's top stretched 1.3x upwards; TEX_VIEW with the body's hue
    turned by 120 degrees (and the body's region); TEX_VIEW 1.3x taller and recoloured, with
    the recoloured pixels, for the hybrid edit."""
    import torch

    from edit.scene import load_scene
    from edit.targets import recolor_region, stretch_axis, write_rgba
    from recon.rundir import RunDir
    from render.io import read_label_map, write_mask

    out.mkdir()
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        scene = load_scene(run, device="cpu")
        frames = RunDir(run).load_cameras().frames
        background = scene.background().detach().numpy()

        view = scene.render_view(frames[GEO_VIEW])
        rows = np.nonzero((view["opacity"] > 0.5).any(axis=1))[0]
        middle = float(rows.min() + rows.max()) / 2
        top = np.zeros_like(view["opacity"])
        top[: int(middle)] = 1.0
        image, alpha = stretch_axis(view["rgb"], view["opacity"], "y", 1.3, middle, top)
        write_rgba(out / "taller.png", image, alpha, background=background)

        camera = frames[TEX_VIEW]
        view = scene.render_view(camera)
        body = read_label_map(capture / "labels" / camera.name) == BODY
        write_mask(out / "body.png", body)
        green = recolor_region(view["rgb"], body, 120.0)
        write_rgba(out / "green.png", green, view["opacity"], background=background)
        tall, alpha = stretch_axis(view["rgb"], view["opacity"], "y", 1.3)
        tall_green, _ = stretch_axis(green, view["opacity"], "y", 1.3)
        write_rgba(out / "tall_green.png", tall_green, alpha, background=background)
        write_mask(out / "tall_green_region.png", np.abs(tall_green - tall).max(axis=-1) > 0.05)
    finally:
        torch.set_num_threads(threads)
    return out


def training_stage(name: str, source, args, folder: str, **kwargs) -> Stage:
    """A stage trained by recon.training.Trainer into WORK/FOLDER (via FOLDER.partial)."""
    return Stage(
        name,
        source,
        args,
        outputs=(folder,),
        partial=(folder + ".partial",),
        checkpoint=folder + ".partial/checkpoint.pt",
        **kwargs,
    )


def edit_stage(name: str, source, options: list, **kwargs) -> Stage:
    return training_stage(
        name,
        source,
        lambda work: ["edit", work / "run", "--name", name, *options],
        f"run/edits/{name}",
        **kwargs,
    )


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    return tmp_path_factory.mktemp("faults")


@pytest.fixture(scope="module")
def references(base) -> dict[str, Reference]:
    """Every stage's uninterrupted run, timed; after the fit two lanes at once (features ->
    texture -> hybrid edit; geometry edit -> render -> export), as the kill points run two at
    once too (T is measured under the load the kill points run under)."""
    capture = synth(base)
    refs = {}
    recon = Stage(
        "recon",
        None,
        lambda work: ["recon", capture, "--out", work / "run", "--hull-resolution", 64],
        outputs=("run",),
        protected=(str(capture),),
        special={
            "run": {
                "proxy_mesh.ply": same_mesh,
                "recon_state.json": same_recon_record,
                "recon_report.json": same_recon_record,
            }
        },
    )
    refs["recon"] = reference_run(recon, base)
    fit = training_stage(
        "fit", refs["recon"].run, lambda work: ["fit", work / "run", *FIT], "run/template"
    )
    refs["fit"] = reference_run(fit, base)
    targets = make_targets(refs["fit"].run, capture, base / "targets")

    def lane_features_texture():
        features = training_stage(
            "features",
            refs["fit"].run,
            lambda work: ["features", work / "run", *FEATURES],
            "run/features",
        )
        refs["features"] = reference_run(features, base)
        texture = ["--mode", "texture", "--target", targets / "green.png"]
        texture += ["--region", targets / "body.png", "--view", TEX_VIEW, *TEXTURE]
        special = {"run/edits/texture": EDIT_CHECKPOINT}
        stage = edit_stage("texture", refs["features"].run, texture, special=special)
        refs["texture"] = reference_run(stage, base)
        hybrid = ["--mode", "hybrid", "--target", targets / "tall_green.png"]
        hybrid += ["--region-texture", targets / "tall_green_region.png", "--view", TEX_VIEW]
        special = {"run/edits/hybrid": EDIT_CHECKPOINT}
        stage = edit_stage("hybrid", refs["features"].run, hybrid + HYBRID, special=special)
        refs["hybrid"] = reference_run(stage, base)

    def lane_geometry_outputs():
        geometry = ["--target", targets / "taller.png", "--view", GEO_VIEW, *GEOMETRY]
        refs["geometry"] = reference_run(edit_stage("geometry", refs["fit"].run, geometry), base)
        source = refs["geometry"].run
        render = Stage(
            "render",
            source,
            lambda work: ["render", work / "run", "--out", work / "render", *RENDER],
            outputs=("render",),
        )
        refs["render"] = reference_run(render, base)
        export = Stage(
            "export",
            source,
            lambda work: ["export", work / "run", "--out", work / "mesh.ply", "--edit", "geometry"],
            outputs=("mesh.ply",),
        )
        refs["export"] = reference_run(export, base)

    with ThreadPoolExecutor(2) as lanes:
        for lane in [lanes.submit(lane_features_texture), lanes.submit(lane_geometry_outputs)]:
            lane.result()
    return refs


# ---- the kill points --------------------------------------------------------------------------
POINTS: list[str] = []


@pytest.fixture(scope="module", autouse=True)
def _summary(base):
    """Prints (pytest -s) and writes every kill point: where it fell, what it left."""
    yield
    (base / "kill_points.txt").write_text("\n".join(POINTS) + "\n")
    print("\n" + "\n".join(POINTS))


# kill points timed from the start (fractions of T) or from the first checkpoint (fractions of
# the reference run's time from its first checkpoint to its end)
WINDOWS = {"start": (0.3, 0.85), "checkpoint": (0.0, 0.6)}


def check_kills(reference: Reference, base, kinds: tuple[str, ...]) -> list[KillPoint]:
    """The stage's kill points, two at a time (see `kill_and_rerun`): "start": SIGKILL after a
    seeded random delay in [0.3 T, 0.85 T]; "checkpoint": after the first checkpoint, a seeded
    random fraction in [0, 0.6] of the time the reference run took from there to its end (the
    re-run resumes from a checkpoint); "at MODULE:ATTR N": a code point. Each one asserts the
    re-run's result. At least one must have killed the stage before it had finished: a run
    that had finished before its kill does not count (the machine may be less loaded than when
    T was measured), so when none did, the first timed point is tried again, up to twice,
    sooner (a "start" point within [0.3, 0.85] x 0.75 of the fastest run's time)."""
    name, t = reference.stage.name, reference.seconds

    def attempt(i: int, kind: str, scale: float, tag: int) -> KillPoint:
        rng = random.Random(f"{SEED}:{name}:{i}:{tag}")
        fraction = rng.uniform(*WINDOWS[kind]) if kind in WINDOWS else 0.0
        return kill_and_rerun(reference, base, kind, scale * fraction, f"{i}-{tag}")

    with ThreadPoolExecutor(2) as pool:
        futures = [pool.submit(attempt, i, kind, 1.0, 0) for i, kind in enumerate(kinds)]
        points = [f.result() for f in futures]
    timed = [i for i, kind in enumerate(kinds) if kind in WINDOWS]
    for retry in (1, 2):
        if any(p.mid_stage for p in points) or not timed:
            break
        kind = kinds[timed[0]]
        fastest = min(p.seconds for p in points)
        scale = min(1.0, fastest / t) * 0.75**retry if kind == "start" else 0.5**retry
        points.append(attempt(timed[0], kind, scale, retry))
    POINTS.extend(f"{p.describe(name)} [T {t:.1f} s]" for p in points)
    assert any(p.mid_stage for p in points), (
        f"{name}: no kill point fell before the stage had finished (T = {t:.1f} s): "
        + "; ".join(p.describe(name) for p in points)
    )
    return points


# the kill points of each stage (see `kill_and_rerun`): recon also inside its normalize stage,
# after it kept two depth maps aside and rewrote the first of them in the run's units (before
# it recorded itself as done); the geometric edit also while its second checkpoint is written
# (the temporary file complete, not yet renamed onto checkpoint.pt)
KILL_POINTS = {
    "recon": ("start", "at recon.recon_stages:write_depth 4"),
    "fit": ("start", "checkpoint"),
    "features": ("start", "checkpoint"),
    "geometry": ("start", "checkpoint", "at torch:save 2"),
    "texture": ("start", "checkpoint"),
    "hybrid": ("start", "checkpoint"),
    "render": ("start", "start"),
    "export": ("start", "start"),
}


@pytest.mark.parametrize("stage", list(KILL_POINTS))
def test_a_stage_killed_then_run_again_equals_an_uninterrupted_run(references, base, stage):
    check_kills(references[stage], base, KILL_POINTS[stage])
