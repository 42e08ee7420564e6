#!/usr/bin/env bash
# Build the C fixed-rate controller (controller.c) over a generated compensator.
#
#   deploy/c/build.sh GEN_DIR [OUT_DIR] [PREFIX]   (default: build/c, torchhys_comp;
#                                                    binary OUT_DIR/controller)
#
# GEN_DIR holds PREFIX.h and PREFIX.c from `torchhys export --format c --out GEN_DIR`. Two
# compiler lines: the generated file as strict C99, the controller with _GNU_SOURCE for its
# POSIX/Linux calls (clock_nanosleep, sched_setaffinity):
#   cc -std=c99 -O2 -Wall -Wextra -Werror -pedantic -c GEN_DIR/PREFIX.c
#   cc -std=c99 -O2 -D_GNU_SOURCE -I GEN_DIR controller.c PREFIX.o -lm
# Environment: CC (default cc), CFLAGS (added to both, e.g. -O3 -march=native; -DCOMP_ADAPT
# for files exported with adapt="rls" or "nlms": the controller's adaptive mode, controller.c).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
GEN=${1:?usage: build.sh GEN_DIR [OUT_DIR] [PREFIX]}
OUT=${2:-build/c}
PREFIX=${3:-torchhys_comp}
CC=${CC:-cc}
read -r -a EXTRA <<<"${CFLAGS:-}"
mkdir -p "$OUT"
"$CC" -std=c99 -O2 -Wall -Wextra -Werror -pedantic "${EXTRA[@]}" -I "$GEN" \
  -c "$GEN/$PREFIX.c" -o "$OUT/$PREFIX.o"
"$CC" -std=c99 -O2 -D_GNU_SOURCE -Wall -Wextra -Werror -pedantic "${EXTRA[@]}" -I "$GEN" \
  -DCOMP="$PREFIX" -DCOMP_HEADER="\"$PREFIX.h\"" \
  -o "$OUT/controller.tmp.$$" "$HERE/controller.c" "$OUT/$PREFIX.o" -lm
mv -f "$OUT/controller.tmp.$$" "$OUT/controller"
echo "$OUT/controller"
