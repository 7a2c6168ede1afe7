"""Texture editing against ground truth: a grid of object x texture edit kind x method.

    python bench/bench_edit_texture.py --out bench/out/edit_texture [--quick]
        [--objects toycar figurine spot avocado bob mug chair] [--edits hue stripes one_sided]
        [--methods ours naive no_compositor template] [--no-features] [--tag T]
    python bench/bench_edit_texture.py --out DIR --memory RUN [--sizes 256 512]

For each object (default: bench_objects.GRID_OBJECTS): a synthetic turntable (DIR/OBJECT/synth,
with the `hue` GT edit), `sine recon` (known poses), `sine fit` (defaults) and, unless
--no-features, `sine features` (semantic masks; else the painted region lifted onto the proxy).
One template serves every kind: each other kind's GT is `sine synth --edit texture` into
DIR/OBJECT/gt_KIND with the base capture's cameras (`cameras_from`; reused when its edit.json
exists). The texture edit kinds (TEXTURE_KINDS, per-object overrides in KIND_OVERRIDES):
- hue: the object's suggested part, hue rotated by 120 degrees (the base synth, as before);
- stripes: a painted pattern, not a plain recolour: two-colour (magenta, cyan) horizontal stripes
  0.08 wide (a decal) over the suggested part (the chair's thin seat: bands across x);
- one_sided: a painting on ONE side of the object only: a disc decal (magenta, a cyan ring) on the
  +y side of the suggested part (toycar, figurine, chair, bob are mirror-symmetric across y = 0:
  the -y side must stay as it is; on the chair's thin seat the disc, projected along y, is a band
  over the seat's +y half; avocado: its skin, the cut face is -y); spot faces +y (mirror plane
  x = 0): on its +x side (the neck's); bob: on its ring (part 1; its part above the middle misses
  the disc's line); the mug: its handle (part 2, on the +x side only) painted magenta (the mug's
  mirror plane y = 0 maps the handle onto itself: there, mirroring is no error).
Every method edits from ONE view (aligned case): the target is the kind's ground-truth edited image
of the training view where that GT edit changes the most pixels (view K, per kind); the painted
region (what a user paints in view K): a recolour's part, its GT label in view K; a decal, the
pixels the GT edit changed in view K dilated by 2 px (the pattern, not the whole part). Edits are
named METHOD+TAG for hue (earlier results are reused) and KIND_METHOD+TAG otherwise. Scored on
held-out edited views (every 4th view around the ring, view K excluded: the far side of the ring
sees parts of the part that view K does not; with few views, e.g. 16, a one-sided disc may be in
none of them: PSNR edit "-") against the kind's ground truth:
- heldout_psnr (PSNR obj): object pixels (GT mask or rendered opacity > 0.5);
  heldout_psnr_edited (PSNR edit): the pixels the GT edit changed; heldout_ssim (whole image);
- unedited_psnr: the edit vs the template's own rendering where the GT edit did not change the
  view (on the object): does the rest stay intact? (one_sided: the unpainted -y side counts here;
  a mean of per-view dB: a leak seen in one view only weighs little); unedited_psnr_pooled:
  one PSNR over every view's unedited pixels together (such a leak counts fully);
- mirrored: the edit's verdict on mirroring view K's painting across the proxy's mirror plane
  (metrics.json "mirror": mirrored, by, agreement): a one-sided painting must not be mirrored.
Writes DIR/results.json ({"cases": [...]}; one case per object x kind x method), per case
DIR/<object>_<kind><tag>_sheet.png (rows: held-out views; columns: template | each method |
ground truth), and prints one markdown table (object | edit | method | PSNR obj | PSNR edit |
SSIM | unedited | unedited pooled | mirrored | s). `--quick`: toycar and mug, hue and one_sided, ours + naive,
300 steps (--objects / --edits / --methods / --iterations still choose).

`--reference OBJECT`: the unaligned case: each object's part (GT label in the editing view as the
region) takes the look of a render of OBJECT (e.g. avocado) given as `--reference`; writes the
before/after previews of 4 views as DIR/<object>_reference_OBJECT_sheet.png and the DINO CLS
distance to the photo before / after into DIR/reference.json. `--reference-backdrop R,G,B`
gives it as a photo without alpha on a plain backdrop (what `--reference-mask` keys).

`--memory RUN`: peak memory of one texture step (one L_tex view at each of --sizes px, DINO at 224,
compositor, L_reg) with deferred back-propagation (tiles of 128 px, F_dT on at most 32768
samples at a time) and, for contrast, direct back-propagation, each in a fresh subprocess: a thread samples the process's resident memory (/proc/self/statm) every
millisecond; reported is the peak during the second step minus the resident memory just before it
(the first step warms up), and the absolute peak. Writes DIR/memory.json.
"""

from __future__ import annotations

import os

os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from bench_objects import GRID_OBJECTS, case_name, gt_edit_capture, synth_source  # noqa: E402

VARIANTS = {
    "ours": {},
    "naive": {"method": "naive"},
    "no_compositor": {"compositor": False},
    "template": None,  # no edit at all: what the template scores (context for the others)
    # the grouped ablation (bench/MECHANISMS.md section 5): each beyond-paper group switched off
    "no_fitted_transform": {"fit_transform": False, "quadratic_transform": False},
    "residual_head": {"compositor_head": "residual"},  # also no part colour, no fitted transform
    "no_mirroring": {"symmetric_auto": False, "keep_seen": False},
    "no_keep_seen": {"keep_seen": False},
    "no_gate_vote": {"gate_vote": False},
    "no_mask_spatial": {"mask_spatial": 0.0},
}


# the grid's GT texture edit kinds: `recon.synth.SynthConfig` options (the part: the object's
# suggestion unless given); `hue` is the base synth's own edit (work/synth)
DECAL_COLORS = [0.85, 0.1, 0.65, 0.1, 0.8, 0.85]  # magenta, cyan: unlike every object's colours
DISC = {"edit_texture_operation": "decal", "edit_decal": "disc", "edit_decal_colors": DECAL_COLORS}
TEXTURE_KINDS = {
    # the object's suggested part, hue rotated by 120 degrees
    "hue": {},
    # a painted pattern: two-colour stripes (horizontal bands, 0.08 wide) over the suggested part
    "stripes": {
        "edit_texture_operation": "decal",
        "edit_decal": "stripes",
        "edit_decal_colors": DECAL_COLORS,
    },
    # a painting on one side only: a disc (radius 0.08, a ring to 0.12) on the +y side of the
    # suggested part; its mirror image across y = 0 stays unpainted
    "one_sided": {**DISC, "edit_decal_axis": [0.0, 1.0, 0.0]},
}
# per-object replacements of a kind's options (where the kind's own miss the point)
KIND_OVERRIDES = {
    # the chair's seat is thinner than a band: horizontal stripes would paint it one colour;
    # bands across x instead (across the seat's planks)
    ("chair", "stripes"): {**TEXTURE_KINDS["stripes"], "edit_decal_axis": [1.0, 0.0, 0.0]},
    # spot faces +y (mirror plane x = 0): the disc on its +x side (the neck's side)
    ("spot", "one_sided"): {**DISC, "edit_decal_axis": [1.0, 0.0, 0.0]},
    # bob's part above the middle (2) is the head and the ring's top, not on the disc's line:
    # the ring below (1), on its +y side
    ("bob", "one_sided"): {**DISC, "edit_decal_axis": [0.0, 1.0, 0.0], "edit_part": 1},
    # the mug: its one-sided part is the handle (+x side only), painted one colour (magenta; its
    # `hue` kind already rotates the handle's hue)
    ("mug", "one_sided"): {"edit_part": 2, "edit_color": [0.85, 0.1, 0.65]},
}
QUICK = {"objects": ["toycar", "mug"], "edits": ["hue", "one_sided"], "methods": ["ours", "naive"]}


def kind_options(obj: str, kind: str) -> dict:
    """The `SynthConfig` texture-edit options of GT edit `kind` on object `obj` (its case name)."""
    return KIND_OVERRIDES.get((obj, kind), TEXTURE_KINDS[kind])


def edit_name(kind: str, method: str, tag: str = "") -> str:
    """The edit's name in the shared run: METHOD+TAG for hue (earlier results), else KIND_..."""
    return f"{method}{tag}" if kind == "hue" else f"{kind}_{method}{tag}"


def gt_dir(syn: Path) -> Path:
    """The texture GT edit's folder in the synth folder `syn`."""
    return syn / "edits" / "texture"


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return 10.0 * np.log10(1.0 / max(mse, 1e-12))


def prepare_object(
    name, work: Path, size, views, fit_iterations, features: bool, fit_options: dict | None = None
):
    from edit.feature_field_fit import FeaturesConfig, distill_features
    from recon.fit import fit_template
    from recon.fit_config import FitConfig
    from recon.ingest import IngestConfig
    from recon.pipeline import run_recon
    from recon.recon_config import ReconConfig
    from recon.rundir import RunDir
    from recon.synth import SynthConfig, synthesize

    syn, run = work / "synth", RunDir(work / "run")
    if not (gt_dir(syn) / "edit.json").is_file():
        source = synth_source(name)
        synthesize(
            SynthConfig(out=syn, views=views, width=size, height=size, edit=["texture"], **source),
            progress=False,
        )
    if not run.proxy_mesh.is_file():
        run_recon(syn, run, ReconConfig(), IngestConfig(width=size))
    fit_cfg = FitConfig(previews=0, **(fit_options or {}))
    if fit_iterations is not None:
        fit_cfg.iterations = fit_iterations
    fit = fit_template(run.root, fit_cfg, progress=False)
    if features:
        distill_features(run.root, FeaturesConfig(previews=0), progress=False)
    return syn, run, fit


def gt_edit(source: str, work: Path, kind: str, size: int, views: int) -> Path:
    """The synth folder of the object's GT texture edit `kind`: work/synth for hue, else
    `gt_edit_capture`'s."""
    if kind == "hue":
        return work / "synth"
    options = kind_options(case_name(source), kind)
    return gt_edit_capture(source, work, kind, size, views, edit=["texture"], **options)


def changed_pixels(syn: Path, name: str) -> np.ndarray:
    """[H, W] bool: pixels the GT texture edit of synth folder `syn` changed in view `name`."""
    from render.io import read_image

    orig = read_image(syn / "images" / name)
    edited = read_image(gt_dir(syn) / "images" / name)
    return np.abs(orig - edited).max(axis=-1) > 0.02


def pick_edit_view(run, syn: Path) -> int:
    """The training view where the GT edit changes the most pixels."""
    counts = [
        (int(changed_pixels(syn, cam.name).sum()), k)
        for k, cam in enumerate(run.load_cameras().frames)
        if cam.split == "train"
    ]
    return max(counts)[1]


def open_object(object_dir: Path, threads: int = 0, kind: str = "hue"):
    """(run, the kind's synth folder, cameras, edit view K) of a finished DIR/OBJECT folder of
    this bench, for the diagnostics that read it (`threads`: torch threads, 0 leaves the
    default)."""
    import torch

    from recon.rundir import RunDir

    if threads:
        torch.set_num_threads(threads)
    run = RunDir(object_dir / "run")
    syn = object_dir / ("synth" if kind == "hue" else f"gt_{kind}")
    return run, syn, run.load_cameras().frames, pick_edit_view(run, syn)


def heldout_views(n_views: int, k: int) -> list[int]:
    """The views scored: every 4th view around the ring, the edited view K excluded."""
    return [v for v in range(0, n_views, 4) if v != k]


def part_label(syn: Path, name: str) -> np.ndarray:
    """[H, W] bool: the GT edit's part in the view of image `name` (its GT labels)."""
    from render.io import read_json, read_label_map

    part = read_json(gt_dir(syn) / "edit.json")["part"]
    return read_label_map(syn / "labels" / Path(name).with_suffix(".png").name) == part


DECAL_REGION_DILATE = 2  # px: a decal's painted region, the pixels its GT changed grown by this


def painted_region(syn: Path, cam, out: Path) -> Path:
    """What the user paints in the view, as a white-on-black PNG: a recolour's part (its GT
    labels); a decal's pattern (the pixels the GT edit changed, dilated by DECAL_REGION_DILATE
    px, a disc of that radius)."""
    import cv2

    from render.io import read_json, write_mask

    if read_json(gt_dir(syn) / "edit.json").get("operation") == "decal":
        r = DECAL_REGION_DILATE
        disc = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
        changed = changed_pixels(syn, cam.name).astype(np.uint8)
        write_mask(out, cv2.dilate(changed, disc) > 0)
    else:
        write_mask(out, part_label(syn, cam.name))
    return out


def score(run, syn: Path, scene, template, views: list[int]) -> tuple[dict, list]:
    from skimage.metrics import structural_similarity

    from render.io import read_image, read_mask

    frames = run.load_cameras().frames
    rows, per = [], {"psnr": [], "edited": [], "ssim": [], "unedited": []}
    pooled = []  # every held-out view's unedited pixels' squared errors, for one pooled PSNR
    for k in views:
        cam = frames[k]
        gt = read_image(gt_dir(syn) / "images" / cam.name)
        gt_mask = read_mask(gt_dir(syn) / "masks" / cam.name)
        changed = changed_pixels(syn, cam.name)
        out = scene.render_view(cam)
        tmpl = np.clip(template.render_view(cam)["rgb"], 0, 1)
        pred = np.clip(out["rgb"], 0, 1)
        obj = gt_mask | (out["opacity"] > 0.5)
        per["psnr"].append(psnr(pred[obj], gt[obj]))
        per["ssim"].append(float(structural_similarity(gt, pred, channel_axis=2, data_range=1.0)))
        if changed.any():
            per["edited"].append(psnr(pred[changed], gt[changed]))
        unchanged = gt_mask & ~changed
        if unchanged.any():
            per["unedited"].append(psnr(pred[unchanged], tmpl[unchanged]))
            pooled.append(((pred[unchanged] - tmpl[unchanged]) ** 2).ravel())
        rows.append((tmpl, pred, gt))
    mean = lambda xs: float(np.mean(xs)) if xs else None  # noqa: E731
    metrics = {
        "heldout_psnr": mean(per["psnr"]),
        "heldout_psnr_edited": mean(per["edited"]),
        "heldout_ssim": mean(per["ssim"]),
        "unedited_psnr": mean(per["unedited"]),
        # one PSNR over every view's unedited pixels: a leak seen in one view counts fully (the
        # mean of per-view dB above lets the clean views outweigh it)
        "unedited_psnr_pooled": (
            float(10 * np.log10(1 / max(np.concatenate(pooled).mean(), 1e-12))) if pooled else None
        ),
        "heldout_views": len(views),
    }
    return metrics, rows


# ---- peak memory of one step ----------------------------------------------------------------
def _rss_bytes() -> int:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")


def memory_child(run_dir: str, size: int, mode: str) -> dict:
    """One L_tex view at `size` px: two steps, the second measured (see the module doc)."""
    import threading

    import torch

    from edit.compositor import Compositor
    from edit.deferred import deferred_backward, direct_backward
    from edit.dino import load_dino
    from edit.texture_field import TextureField
    from edit.texture_loss import TextureLoss
    from edit.texture_training import edited_image
    from edit.texture_views import sample_view, scaled_camera
    from recon.fit import load_fitted
    from recon.fit_proxy import make_sampler
    from recon.rundir import RunDir
    from render.template_field import freeze

    torch.set_num_threads(max(1, int(os.environ.get("THREADS", "1"))))
    run = RunDir(run_dir)
    template, background, fit_cfg = load_fitted(run.root)
    freeze(template)
    camera = scaled_camera(run.load_cameras().frames[0], size)
    sampler = make_sampler(fit_cfg, run)
    view = sample_view(camera, template, sampler, background, features=True)
    h, w = view.size
    # F_dT as the default edit's: reading the template's geometry feature per sample
    texture = TextureField(template.grid.cfg, cond_dim=template.cfg.geo_feat_dim)
    comp = Compositor()
    with torch.no_grad():
        texture.mlp[-1].weight.normal_(0, 0.1)
    dino = load_dino(torch.device("cpu"))
    dino.requires_grad_(False)
    image = view.template_rgb.reshape(h, w, 3).permute(2, 0, 1)[None]
    loss = TextureLoss(dino, image[0], 1.0, 1.0)
    sim = loss.template_similarity(image)
    editable = view.opacity > 0.5

    def loss_fn(leaves):
        out = leaves[0]["rgb"]
        tex = loss.terms(out.permute(2, 0, 1)[None], template_sim=sim)
        reg = ((out.reshape(-1, 3) - view.template_rgb)[~editable] ** 2).sum(-1).mean()
        return tex["cls"] + tex["structure"] + reg, None

    def step():
        if mode == "deferred":  # tiles of 128 px, F_dT on 32768 samples at a time
            images = [edited_image(view, texture, comp, 128, 32768)]
        else:  # the whole image in one piece, one graph over every sample
            images = [edited_image(view, texture, comp, max(h, w), None)]
        if mode == "deferred":
            deferred_backward(images, loss_fn)
        else:
            direct_backward(images, loss_fn)

    step()  # warm-up
    texture.zero_grad(), comp.zero_grad()
    peak, stop = [0], threading.Event()

    def watch():
        while not stop.is_set():
            peak[0] = max(peak[0], _rss_bytes())
            time.sleep(0.001)

    before = _rss_bytes()
    thread = threading.Thread(target=watch, daemon=True)
    thread.start()
    t0 = time.perf_counter()
    step()
    seconds = time.perf_counter() - t0
    stop.set()
    thread.join()
    peak[0] = max(peak[0], _rss_bytes())
    return {
        "size": size,
        "mode": mode,
        "pixels": view.n_pixels,
        "samples": int(view.points.shape[0]),
        "step_peak_mib": (peak[0] - before) / 2**20,
        "process_peak_mib": peak[0] / 2**20,
        "seconds": seconds,
    }


def memory_bench(run_dir: Path, sizes: list[int], out: Path) -> list[dict]:
    from render.io import write_json

    rows = []
    for size in sizes:
        for mode in ("deferred", "direct"):
            root = str(Path(__file__).resolve().parents[1])
            code = (
                f"import json, sys; sys.path.insert(0, {root!r}); "
                "from bench.bench_edit_texture import memory_child; "
                f"print(json.dumps(memory_child({str(run_dir)!r}, {size}, {mode!r})))"
            )
            res = subprocess.run(
                [sys.executable, "-c", code], capture_output=True, text=True, check=True
            )
            rows.append(json.loads(res.stdout.strip().splitlines()[-1]))
            print(json.dumps(rows[-1]), flush=True)
    write_json(out / "memory.json", rows)
    print(
        f"\n{'size':>5s} {'mode':9s} {'pixels':>7s} {'samples':>8s} {'step MiB':>9s} {'peak MiB':>9s} {'s':>6s}"
    )
    for r in rows:
        print(
            f"{r['size']:5d} {r['mode']:9s} {r['pixels']:7d} {r['samples']:8d} "
            f"{r['step_peak_mib']:9.1f} {r['process_peak_mib']:9.1f} {r['seconds']:6.2f}"
        )
    return rows


# ---- unaligned: a reference photo of another object ------------------------------------------
def reference_photo(name: str, out: Path, size: int, backdrop=None) -> tuple[Path, Path]:
    """A render of another object (`sine synth`, 8 views, the second one) as an RGBA photo,
    and the photo the edit is given: that one, or with `backdrop` (R, G, B) as an opaque photo
    without alpha on a backdrop of that colour, lit unevenly (+-0.06 top to bottom) and noisy
    (sigma 0.01), as a photo on a plain backdrop is -> (RGBA path, given path)."""
    from edit.targets import write_rgba
    from recon.synth import SynthConfig, synthesize
    from render.io import read_image, read_mask, write_image

    syn = out / f"reference_{case_name(name)}"
    if not (syn / "cameras.json").is_file():
        source = synth_source(name)
        synthesize(SynthConfig(out=syn, views=8, width=size, height=size, **source), progress=False)
    frame = sorted((syn / "images").glob("*.png"))[1]
    photo = out / f"reference_{case_name(name)}.png"
    rgb, alpha = read_image(frame), read_mask(syn / "masks" / frame.name).astype(np.float32)
    write_rgba(photo, rgb, alpha)
    if backdrop is None:
        return photo, photo
    h, w = alpha.shape
    light = np.linspace(0.06, -0.06, h, dtype=np.float32)[:, None, None]
    noise = np.random.default_rng(0).normal(0.0, 0.01, (h, w, 3)).astype(np.float32)
    behind = np.clip(np.asarray(backdrop, np.float32) + light + noise, 0, 1)
    opaque = out / f"reference_{case_name(name)}_on_backdrop.png"
    write_image(opaque, rgb * alpha[..., None] + behind * (1 - alpha[..., None]))
    return photo, opaque


def reference_color_distances(syn: Path, previews: list[Path], photo: Path) -> dict:
    """How far the edited part's colours are from the photo's object colours, before and after:
    the sliced Wasserstein distance (64 fixed random directions, squared, x 1000) between the
    part's pixels in the previews (template | edit; the part's GT label in each view) and the
    photo's opaque pixels."""
    import torch

    from edit.texture_loss import sliced_wasserstein
    from edit.texture_setup import read_reference
    from render.io import read_image

    reference = torch.from_numpy(read_reference(photo, (1.0, 1.0, 1.0)).colors)
    gen = torch.Generator().manual_seed(0)
    directions = torch.nn.functional.normalize(torch.randn(64, 3, generator=gen), dim=1)
    before, after = [], []
    for path in previews:
        pair = read_image(path)
        w = pair.shape[1] // 2
        inside = part_label(syn, path.name)
        for half, out in ((pair[:, :w], before), (pair[:, w:], after)):
            colours = torch.from_numpy(np.ascontiguousarray(half[inside]))
            out.append(1000 * float(sliced_wasserstein(colours, reference, directions)))
    return {
        "color_distance_before": float(np.mean(before)),
        "color_distance_after": float(np.mean(after)),
    }


def unaligned(args, source: str, reference: str) -> dict:
    """Ours with --reference: the object's part (its GT label in the editing view) takes the
    look of the reference photo; CLS distances to the photo before / after on 4 views."""
    from edit.texture_config import TextureEditConfig
    from edit.texture_edit import run_texture_edit
    from render.io import read_image, write_image

    obj = case_name(source)
    work = args.out / obj
    syn, run, _ = prepare_object(
        source, work, args.size, args.views, args.fit_iterations, not args.no_features, args.fit_set
    )
    photo, given = reference_photo(reference, args.out, args.size, args.reference_backdrop)
    k = pick_edit_view(run, syn)
    region = painted_region(syn, run.load_cameras().frames[k], work / "region.png")
    options = {k_: json.loads(v) for k_, v in (kv.split("=", 1) for kv in args.set)}
    cfg = TextureEditConfig(previews=4, threads=args.threads, **options)
    if args.iterations:
        cfg.iterations = args.iterations
    name = f"reference_{case_name(reference)}{args.tag}"
    t0 = time.perf_counter()
    m = run_texture_edit(
        run.root, k, None, name, cfg, region=region, reference=given, progress=False
    )
    previews = sorted((run.edit(name) / "previews").glob("*.png"))
    sheet = np.concatenate([read_image(p) for p in previews], axis=0)
    write_image(args.out / f"{obj}_{name}_sheet.png", sheet)
    colors = reference_color_distances(syn, previews, photo)
    case = {
        "object": obj,
        "reference": case_name(reference),
        "edit_view": k,
        "cls_distance_before": m["preview_cls_distance_before"],
        "cls_distance_after": m["preview_cls_distance_after"],
        **colors,
        "unedited_view_psnr": m.get("unedited_view_psnr"),
        "mask_source": m.get("mask_source"),
        "reference_pixels": m.get("reference_pixels"),
        "iterations": m["iterations"],
        "seconds": m.get("total_seconds", time.perf_counter() - t0),
    }
    print(json.dumps(case), flush=True)
    return case


# ---- the benchmark --------------------------------------------------------------------------
def main() -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--out", type=Path, required=True, help="work and results folder")
    ap.add_argument(
        "--quick",
        action="store_true",
        help=f"{' and '.join(QUICK['objects'])}, {' and '.join(QUICK['edits'])}, "
        f"{' + '.join(QUICK['methods'])}, 300 steps (unless --objects / --edits / --methods / "
        "--iterations are given)",
    )
    ap.add_argument(
        "--objects",
        nargs="+",
        default=None,
        help=f"default: {' '.join(GRID_OBJECTS)} (--reference: toycar figurine spot); or any "
        "mesh file (OBJ/GLB/GLTF/PLY; its part above the middle plane is the part edited), named "
        "by its stem",
    )
    ap.add_argument(
        "--edits",
        nargs="+",
        default=None,
        choices=list(TEXTURE_KINDS),
        help=f"GT texture edit kinds (default: {' '.join(TEXTURE_KINDS)})",
    )
    ap.add_argument(
        "--methods",
        nargs="+",
        default=None,
        choices=list(VARIANTS),
        help="default: ours naive no_compositor",
    )
    ap.add_argument("--size", type=int, default=256, help="image size (square)")
    ap.add_argument("--views", type=int, default=36, help="views on the ring")
    ap.add_argument("--iterations", type=int, default=None, help="edit steps (default: the edit's)")
    ap.add_argument(
        "--fit-iterations", type=int, default=None, help="template steps (default: fit's)"
    )
    ap.add_argument(
        "--no-features",
        action="store_true",
        help="skip `sine features`: masks from the region lifted onto the proxy",
    )
    ap.add_argument("--threads", type=int, default=0, help="torch threads (0: default)")
    ap.add_argument(
        "--set",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="texture-edit options for every method (e.g. w_cls=1e-3); VALUE is read as JSON",
    )
    ap.add_argument(
        "--fit-set",
        nargs="+",
        default=[],
        metavar="KEY=VALUE",
        help="template (`sine fit`) options, e.g. seed=1 average_window=0.15: how much an edit "
        "depends on its template (one run folder per template: give each its own --out)",
    )
    ap.add_argument("--tag", default="", help="suffix of the edits' names (variants side by side)")
    ap.add_argument(
        "--reference",
        help="unaligned case instead: the objects' part takes the look of a render of this "
        "object (e.g. avocado, or a mesh file); before/after previews and CLS distances",
    )
    ap.add_argument(
        "--reference-backdrop",
        type=lambda s: [float(v) for v in s.split(",")],
        help="R,G,B in [0, 1]: give the reference as an opaque photo (no alpha) on a backdrop "
        "of this colour, unevenly lit and noisy; colour distances stay against its object",
    )
    ap.add_argument("--memory", type=Path, help="measure one step's peak memory on this RUN")
    ap.add_argument("--sizes", type=int, nargs="+", default=[256, 512], help="--memory sizes")
    args = ap.parse_args()
    args.fit_set = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.fit_set)}
    args.out.mkdir(parents=True, exist_ok=True)
    if args.memory is not None:
        memory_bench(args.memory, args.sizes, args.out)
        return 0
    if args.quick:
        args.objects = args.objects or list(QUICK["objects"])
        args.edits = args.edits or list(QUICK["edits"])
        args.methods = args.methods or list(QUICK["methods"])
        args.iterations = args.iterations or 300
    args.edits = args.edits or list(TEXTURE_KINDS)
    args.methods = args.methods or ["ours", "naive", "no_compositor"]
    if args.reference:
        from render.io import write_json

        objects = args.objects or ["toycar", "figurine", "spot"]
        cases = [unaligned(args, obj, args.reference) for obj in objects]
        write_json(args.out / f"reference{args.tag}.json", {"cases": cases})
        return 0

    args.objects = args.objects or list(GRID_OBJECTS)
    from edit.scene import load_scene
    from render.io import write_json

    options = {k: json.loads(v) for k, v in (kv.split("=", 1) for kv in args.set)}
    cases = []
    for source in args.objects:
        obj = case_name(source)
        t0 = time.perf_counter()
        work = args.out / obj
        _, run, fit = prepare_object(
            source,
            work,
            args.size,
            args.views,
            args.fit_iterations,
            not args.no_features,
            args.fit_set,
        )
        print(
            f"[{obj}] template: held-out PSNR {fit.get('heldout_psnr', float('nan')):.2f} dB, "
            f"prepared in {time.perf_counter() - t0:.0f} s",
            flush=True,
        )
        template = load_scene(run.root)
        for kind in args.edits:
            syn = gt_edit(source, work, kind, args.size, args.views)
            cases += edit_case(args, obj, kind, syn, work, run, template, options)
            write_json(
                args.out / f"results{args.tag}.json",
                {"cases": cases, "columns": ["template", *args.methods, "ground truth"]},
            )
    print()
    print_table(cases)
    return 0


def edit_case(args, obj: str, kind: str, syn: Path, work: Path, run, template, options: dict):
    """Every method on GT texture edit `kind` (synth folder `syn`) of object `obj` (folder
    `work`) -> its cases; writes the contact sheet DIR/<obj>_<kind><tag>_sheet.png."""
    import dataclasses

    from edit.scene import load_scene
    from edit.texture_config import TextureEditConfig
    from edit.texture_edit import run_texture_edit
    from render.io import read_mask, write_image

    frames = run.load_cameras().frames
    k = pick_edit_view(run, syn)
    cam = frames[k]
    if not changed_pixels(syn, cam.name).any():
        print(f"[{obj}] {kind}: the GT edit changes no training view, skipped", flush=True)
        return []
    views = heldout_views(len(frames), k)
    target = gt_dir(syn) / "images" / cam.name
    region = painted_region(
        syn, cam, work / ("region.png" if kind == "hue" else f"region_{kind}.png")
    )
    cases, columns, rows = [], None, []
    for method in args.methods:
        cfg = TextureEditConfig(previews=0, threads=args.threads, **options)
        cfg = dataclasses.replace(cfg, **(VARIANTS[method] or {}))
        if args.iterations:
            cfg.iterations = args.iterations
        t1 = time.perf_counter()
        name = edit_name(kind, method, args.tag)
        if method == "template":
            m, scene = {}, template
        else:
            m = run_texture_edit(run.root, k, target, name, cfg, region=region, progress=False)
            scene = load_scene(run.root, edit=name)
        seconds = m.get("total_seconds", time.perf_counter() - t1)
        metrics, rows = score(run, syn, scene, template, views)
        case = {
            "object": obj,
            "edit": kind,
            "method": method,
            "options": options,
            **metrics,
            "mirrored": m.get("mirror"),
            "seconds": float(seconds),
            "edit_view": k,
            "region_pixels": int(read_mask(region).sum()),
            "edited_view_psnr_region": m.get("edited_view_psnr_region"),
            "mask_source": m.get("mask_source"),
            "iterations": m.get("iterations"),
        }
        cases.append(case)
        print(json.dumps(case), flush=True)
        columns = [[r[0]] for r in rows] if columns is None else columns  # the template
        for column, r in zip(columns, rows, strict=True):
            column.append(r[1])
    if columns:
        picked = np.linspace(0, len(rows) - 1, min(4, len(rows))).astype(int)
        sheet = np.concatenate(
            [np.concatenate(columns[i] + [rows[i][2]], axis=1) for i in picked], axis=0
        )
        write_image(args.out / f"{obj}_{kind}{args.tag}_sheet.png", sheet)
    return cases


def mirror_cell(verdict: dict | None) -> str:
    """The table's `mirrored` cell: yes / no (the masks' agreement with the mirrored painting)."""
    if not verdict:
        return "-"
    cell = "yes" if verdict.get("mirrored") else "no"
    agreement = verdict.get("agreement")
    if agreement is not None and np.isfinite(agreement):
        cell += f" ({agreement:.2f})"
    elif verdict.get("by") != "auto" or verdict.get("why"):
        cell += f" ({verdict.get('why') or verdict.get('by')})"
    return cell


def print_table(cases: list[dict]) -> None:
    """One markdown table row per case (object x edit kind x method)."""
    fmt = lambda v: "-" if v is None else f"{v:.2f}"  # noqa: E731
    print(
        "| object | edit | method | PSNR obj | PSNR edit | SSIM | unedited | unedited pooled "
        "| mirrored | s |"
    )
    print("|---|---|---|---:|---:|---:|---:|---:|---|---:|")
    for c in cases:
        print(
            f"| {c['object']} | {c['edit']} | {c['method']} | {fmt(c['heldout_psnr'])} | "
            f"{fmt(c['heldout_psnr_edited'])} | {c['heldout_ssim']:.3f} | "
            f"{fmt(c['unedited_psnr'])} | {fmt(c.get('unedited_psnr_pooled'))} | "
            f"{mirror_cell(c['mirrored'])} | {c['seconds']:.0f} |"
        )


if __name__ == "__main__":
    sys.exit(main())
