"""The native (C++) hash-encoding kernels: built once with the system compiler, loaded by ctypes.

`scripts/install.sh` builds the library (`python -m render.native`); otherwise the first use
builds it. The library is cached by the source's hash in `render/csrc/build/` (or, when the
package folder is read-only, `~/.cache/sine/`), so an edited source is rebuilt and a stale
library is never loaded. Without a compiler, or with `SINE_NATIVE=0`, `library()` returns None
and the torch path of `render/hashgrid.py` runs instead (same results, slower).
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import sys
import tempfile
import warnings
from pathlib import Path

import torch

SOURCE = Path(__file__).with_name("csrc") / "hashgrid.cpp"
FLAGS = ["-O3", "-shared", "-fPIC", "-pthread", "-std=c++17", "-ffp-contract=off"]

_library: ctypes.CDLL | None = None
_tried = False

_I64, _PTR = ctypes.c_int64, ctypes.c_void_p
_LEVELS = [_PTR, _PTR, _PTR, _I64]  # res, offsets, dense, log2_table (HashGrid._native_args)
SIGNATURES = {
    # x01, n, table, n_feat, n_levels, *levels, out, threads
    "hash_encode_forward": [_PTR, _I64, _PTR, _I64, _I64, *_LEVELS, _PTR, _I64],
    # x01, n, n_feat, n_levels, *levels, grad_out, grad_table, threads
    "hash_encode_backward_table": [_PTR, _I64, _I64, _I64, *_LEVELS, _PTR, _PTR, _I64],
    # x01, n, table, n_feat, n_levels, *levels, grad_out, grad_x, threads
    "hash_encode_backward_x": [_PTR, _I64, _PTR, _I64, _I64, *_LEVELS, _PTR, _PTR, _I64],
}


def _library_path() -> Path:
    digest = hashlib.sha256(SOURCE.read_bytes() + " ".join(FLAGS).encode()).hexdigest()[:16]
    name = f"sine_hashgrid_{digest}.so"
    local = SOURCE.parent / "build"
    if os.access(SOURCE.parent, os.W_OK):
        return local / name
    return Path.home() / ".cache" / "sine" / name


def compiler() -> str | None:
    """The C++ compiler to build with ($CXX, else c++/g++/clang++ on PATH), or None."""
    for name in (os.environ.get("CXX"), "c++", "g++", "clang++"):
        if name and shutil.which(name):
            return name
    return None


def build(force: bool = False) -> Path:
    """Compiles the library (atomically) unless it is there; returns its path."""
    path = _library_path()
    if path.is_file() and not force:
        return path
    cxx = compiler()
    if cxx is None:
        raise RuntimeError("no C++ compiler found (set CXX or install g++)")
    path.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=path.parent) as tmp:
        out = Path(tmp) / path.name
        proc = subprocess.run(
            [cxx, *FLAGS, str(SOURCE), "-o", str(out)], capture_output=True, text=True
        )
        if proc.returncode != 0:
            raise RuntimeError(f"{cxx} failed:\n{proc.stderr.strip()}")
        os.replace(out, path)
    for stale in path.parent.glob("sine_hashgrid_*.so"):  # builds of older sources
        if stale != path:
            stale.unlink(missing_ok=True)
    return path


def library() -> ctypes.CDLL | None:
    """The loaded kernels, building them on first use; None when unavailable (warned once)."""
    global _library, _tried
    if _tried:
        return _library
    _tried = True
    if os.environ.get("SINE_NATIVE", "1") == "0":
        return None
    try:
        lib = ctypes.CDLL(str(build()))
    except (OSError, RuntimeError) as exc:
        warnings.warn(
            f"native hash-grid kernels unavailable ({exc}); using the slower torch path",
            stacklevel=2,
        )
        return None
    for name, argtypes in SIGNATURES.items():
        fn = getattr(lib, name)
        fn.argtypes, fn.restype = argtypes, None
    _library = lib
    return lib


def pointer(tensor: torch.Tensor) -> int:
    """Address of a contiguous CPU tensor's data (for ctypes)."""
    assert tensor.is_contiguous() and tensor.device.type == "cpu"
    return tensor.data_ptr()


if __name__ == "__main__":  # python -m render.native: build (the install step)
    try:
        print(f"[install] native kernels: {build(force='--force' in sys.argv)}")
    except RuntimeError as exc:
        print(f"[install] native kernels not built ({exc}); the torch path will be used")
