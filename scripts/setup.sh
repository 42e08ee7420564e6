#!/usr/bin/env bash
# Idempotent environment set-up for torchhys.
#   - uses the active virtual environment, or creates ./.venv
#   - installs the CPU wheel torch==2.13.0 first when torch is missing
#     (an unpinned torch would pull several GB of CUDA packages);
#     a torch that is already installed is kept
#   - installs the project (editable) with its train extra (Lightning, jsonargparse,
#     torchmetrics, matplotlib: the `torchhys` command and `make reproduce`), its onnx extra
#     (onnx, onnxscript, onnxruntime: the ONNX export and its checks), its fmu extra (FMPy:
#     the FMU export's checks), its casadi extra (the CasADi export), its fleet extra (Dask distributed:
#     torchhys fleet) and its dev extra (what
#     `make test` needs)
# A stamp file makes a second run start in well under a second.
set -euo pipefail
cd "$(dirname "$0")/.."

TORCH_PIN="torch==2.13.0"
if [ -n "${VIRTUAL_ENV:-}" ]; then
    ENV_DIR="$VIRTUAL_ENV"
else
    ENV_DIR="$PWD/.venv"
fi
PY="$ENV_DIR/bin/python"

if [ "${1:-}" = "--print-python" ]; then
    echo "$PY"
    exit 0
fi

if [ ! -x "$PY" ]; then
    echo "[setup] creating virtual environment in $ENV_DIR"
    python3 -m venv "$ENV_DIR"
    "$PY" -m pip install --quiet --upgrade pip
fi

STAMP="$ENV_DIR/.torchhys-installed"
# check the installed distribution without importing it (importing torch takes seconds)
if [ -f "$STAMP" ] && [ "$STAMP" -nt pyproject.toml ] \
    && "$PY" -c "import importlib.metadata as m; m.version('torchhys')" 2>/dev/null; then
    exit 0
fi

if ! "$PY" -c "import torch" 2>/dev/null; then
    echo "[setup] installing the CPU build $TORCH_PIN"
    # TORCH_PIP_ARGS lets a user point pip at a CPU index, e.g.
    #   TORCH_PIP_ARGS="--index-url https://download.pytorch.org/whl/cpu" make test
    # shellcheck disable=SC2086
    "$PY" -m pip install --quiet "$TORCH_PIN" ${TORCH_PIP_ARGS:-}
fi
echo "[setup] installing torchhys with its train, onnx, fmu, casadi, fleet and dev extras"
"$PY" -m pip install --quiet -e ".[train,onnx,fmu,casadi,fleet,dev]"
touch "$STAMP"
echo "[setup] done: $("$PY" -c 'import torch; print("torch", torch.__version__)')"
