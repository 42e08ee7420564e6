#!/usr/bin/env bash
# Build the fixed-rate controller against the libtorch that ships inside the pip torch wheel.
#
#   deploy/cpp/build.sh [OUT_DIR]        (default: build/cpp; binary OUT_DIR/controller)
#
# Environment: PYTHON (the interpreter whose torch to use, default: python3), CXX (g++).
# The AOTInductor loader is compiled in when the wheel ships its header. One compiler line:
#   g++ -std=c++20 -O2 [-DTORCHHYS_AOTI] controller.cpp -o controller -I$TP/include \
#       -I$TP/include/torch/csrc/api/include -L$TP/lib -ltorch -ltorch_cpu -lc10 \
#       -Wl,-rpath,$TP/lib
# with TP the torch package directory (the parent of torch.utils.cmake_prefix_path's
# "share/cmake"). CMakeLists.txt in this folder builds the same program with CMake.
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
PY=${PYTHON:-python3}
TP=$("$PY" -c "import os, torch; print(os.path.dirname(os.path.dirname(torch.utils.cmake_prefix_path)))")
OUT=${1:-build/cpp}
mkdir -p "$OUT"
AOTI=()
if [ -f "$TP/include/torch/csrc/inductor/aoti_package/model_package_loader.h" ]; then
  AOTI=(-DTORCHHYS_AOTI)
fi
"${CXX:-g++}" -std=c++20 -O2 "${AOTI[@]}" "$HERE/controller.cpp" -o "$OUT/controller.tmp.$$" \
  -I"$TP/include" -I"$TP/include/torch/csrc/api/include" -L"$TP/lib" \
  -ltorch -ltorch_cpu -lc10 -Wl,-rpath,"$TP/lib"
mv -f "$OUT/controller.tmp.$$" "$OUT/controller"
echo "$OUT/controller"
