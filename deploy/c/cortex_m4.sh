#!/usr/bin/env bash
# The generated C on a Cortex-M4 with hardware float, under QEMU, against the host's build.
#
#   deploy/c/cortex_m4.sh OUT_DIR [CKPT] [--model paper|composed] [--adapt none|nlms|rls]
#
# 1. Writes the float32 C files of a small example compensator into OUT_DIR/gen and ref.h,
#    the reference sequence compiled in as a const array. --model paper (the default):
#    deploy/c/example_comp.py, the network of configs/compensator.yaml, normalization fitted
#    on a loop; or CKPT, a checkpoint of the torchhys command. --model composed:
#    deploy/c/example_composed.py, a plain module (4 play operators beside the input -> an
#    nn.GRU of 8 units -> nn.Linear, seeded, trained briefly on the same loop) through
#    torchhys.compose.compose, and torch64.txt, the float64 compensator's commands.
#    --adapt nlms (or rls; --model paper without CKPT): the adaptive step of the same network
#    (to_c's adapt), mcu_main.c built with -DCOMP_ADAPT (a pair at every sample, the
#    adaptive counters compared too).
# 2. Cross-compiles mcu_main.c, the two generated files and the start-up (cortex_m4_startup.c,
#    cortex_m4.ld: a 16-entry vector table, flash at 0x0, RAM at 0x20000000, FPU on, .data
#    copied, .bss zeroed, then newlib's _start) with
#      arm-none-eabi-gcc -mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16 -O2
#    and semihosting through newlib's rdimon (--specs=rdimon.specs -lrdimon).
# 3. Prints flash and RAM (arm-none-eabi-size): the compensator's object alone (code and
#    weights, its step's stack from -fstack-usage) and the whole image (newlib's printf in it).
#    Then the step's cost: QEMU runs with -icount shift=0 (one instruction a virtual ns) and
#    mcu_main.c sums SysTick (25 MHz: 40 instructions a tick) around each step: printed as
#    instructions per step (a Cortex-M4 takes about one cycle an instruction, more with
#    flash wait states and FPU division or square root).
# 4. Runs the image under QEMU (mps2-an386, semihosting), the same files built with the host's
#    cc, and compares the commands: within 1e-4 of their scale (the float32 bound of
#    docs/deployment.md), the counters equal. --model composed also compares the QEMU
#    commands with the float64 torch compensator's (torch64.txt), within 1e-4 of their scale.
#    Exit status 0 when they agree.
#
# Needs: apt-get install -y gcc-arm-none-eabi libnewlib-arm-none-eabi qemu-system-arm
# Environment: PYTHON (an interpreter with torchhys, default: python3), CC (the host's, cc),
# QEMU_TIMEOUT (seconds, default 120).
set -euo pipefail
HERE=$(cd "$(dirname "$0")" && pwd)
PY=${PYTHON:-python3}
USAGE="usage: cortex_m4.sh OUT_DIR [CKPT] [--model paper|composed] [--adapt none|nlms|rls]"
MODEL=paper
ADAPT=none
POS=()
while (($#)); do
  case $1 in
    --model) MODEL=${2:?$USAGE}; shift 2 ;;
    --model=*) MODEL=${1#--model=}; shift ;;
    --adapt) ADAPT=${2:?$USAGE}; shift 2 ;;
    --adapt=*) ADAPT=${1#--adapt=}; shift ;;
    -*) echo "cortex_m4.sh: unknown option $1: $USAGE" >&2; exit 2 ;;
    *) POS+=("$1"); shift ;;
  esac
done
OUT=${POS[0]:?$USAGE}
CKPT=${POS[1]:-}
case $MODEL in
  paper) ;;
  composed) [[ -z $CKPT ]] || { echo "cortex_m4.sh: --model composed takes no CKPT" >&2; exit 2; } ;;
  *) echo "cortex_m4.sh: --model must be paper or composed, got '$MODEL'" >&2; exit 2 ;;
esac
case $ADAPT in
  none) ;;
  nlms|rls) [[ $MODEL == paper && -z $CKPT ]] || {
    echo "cortex_m4.sh: --adapt takes the paper example (no CKPT, no --model composed)" >&2
    exit 2; } ;;
  *) echo "cortex_m4.sh: --adapt must be none, nlms or rls, got '$ADAPT'" >&2; exit 2 ;;
esac
((${#POS[@]} <= 2)) || { echo "cortex_m4.sh: too many arguments: $USAGE" >&2; exit 2; }
for tool in arm-none-eabi-gcc arm-none-eabi-size qemu-system-arm; do
  command -v "$tool" >/dev/null || {
    echo "cortex_m4.sh: $tool not found: apt-get install -y gcc-arm-none-eabi" \
      "libnewlib-arm-none-eabi qemu-system-arm" >&2
    exit 2
  }
done
mkdir -p "$OUT/gen"
GEN=$(cd "$OUT/gen" && pwd)
OUT=$(cd "$OUT" && pwd)

# 1. the C files and the reference sequence
rm -f "$GEN/torch64.txt"
if [[ $MODEL == composed ]]; then
  "$PY" "$HERE/example_composed.py" "$GEN" --dtype float32 >/dev/null
else
  "$PY" "$HERE/example_comp.py" "$GEN" --dtype float32 ${CKPT:+--ckpt "$CKPT"} \
    --adapt "$ADAPT" >/dev/null
fi

# 2. the Cortex-M4 image
MCU=(-mcpu=cortex-m4 -mthumb -mfloat-abi=hard -mfpu=fpv4-sp-d16 -O2)
STRICT=(-std=c99 -Wall -Wextra -Werror -pedantic)
MAIN_DEFS=()
[[ $ADAPT == none ]] || MAIN_DEFS=(-DCOMP_ADAPT)
arm-none-eabi-gcc "${MCU[@]}" "${STRICT[@]}" -ffunction-sections -fdata-sections \
  -fstack-usage -I "$GEN" -c "$GEN/torchhys_comp.c" -o "$OUT/torchhys_comp.o"
arm-none-eabi-gcc "${MCU[@]}" "${STRICT[@]}" -ffunction-sections -fdata-sections \
  "${MAIN_DEFS[@]}" -I "$GEN" -c "$HERE/mcu_main.c" -o "$OUT/mcu_main.o"
arm-none-eabi-gcc "${MCU[@]}" -std=gnu99 -Wall -Wextra -Werror -ffunction-sections \
  -fdata-sections -c "$HERE/cortex_m4_startup.c" -o "$OUT/startup.o"
arm-none-eabi-gcc "${MCU[@]}" --specs=rdimon.specs -T "$HERE/cortex_m4.ld" \
  -Wl,--gc-sections -Wl,-Map="$OUT/mcu.map" -o "$OUT/mcu.elf" \
  "$OUT/startup.o" "$OUT/mcu_main.o" "$OUT/torchhys_comp.o" -lm -lrdimon

# 3. flash and RAM
read -r c_text c_data c_bss _ < <(arm-none-eabi-size "$OUT/torchhys_comp.o" | tail -n 1)
read -r text data bss _ < <(arm-none-eabi-size "$OUT/mcu.elf" | tail -n 1)
step_stack=$(awk '/torchhys_comp_step/ {print $2}' "$OUT"/torchhys_comp.su)
state=$(grep -o 'STATE_BYTES [0-9]*' "$GEN/torchhys_comp.h" | awk '{print $2}')
echo "compensator (torchhys_comp.o): flash $((c_text + c_data)) B (text $c_text, data $c_data)," \
  "RAM $((c_data + c_bss)) B; state $state B (the caller's); step stack ${step_stack:-?} B"
echo "image (mcu.elf, with newlib and printf): flash $((text + data)) B, RAM $((data + bss)) B" \
  "(data $data, bss $bss) plus stack"

# 4. QEMU against the host
timeout "${QEMU_TIMEOUT:-120}" qemu-system-arm -M mps2-an386 -cpu cortex-m4 -nographic \
  -monitor none -serial none -semihosting-config enable=on,target=native -icount shift=0 \
  -kernel "$OUT/mcu.elf" >"$OUT/qemu.txt" 2>"$OUT/qemu_err.txt"
read -r _ ticks _ steps < <(grep '^ticks ' "$OUT/qemu_err.txt")
echo "step: $((ticks * 40 / steps)) instructions on average over $steps steps (QEMU -icount," \
  "SysTick ticks of 40 instructions)"
"${CC:-cc}" -std=c99 -O2 "${MAIN_DEFS[@]}" -I "$GEN" -o "$OUT/host" "$HERE/mcu_main.c" \
  "$GEN/torchhys_comp.c" -lm
"$OUT/host" >"$OUT/host.txt"
"$PY" - "$OUT/qemu.txt" "$OUT/host.txt" "$GEN/torch64.txt" <<'PYEOF'
import os
import sys

def read(path):
    rows = [line.split() for line in open(path) if line.strip()]
    head, counts = rows[0], rows[-1]
    u = [float(r[1]) for r in rows[1:-1]]
    return head, u, counts

(qh, qu, qc), (hh, hu, hc) = read(sys.argv[1]), read(sys.argv[2])
assert len(qu) == len(hu) > 0, (len(qu), len(hu))
scale = max(1.0, max(abs(v) for v in hu))
gap = max(abs(a - b) for a, b in zip(qu, hu)) / scale
same = sum(a == b for a, b in zip(qu, hu))
ok = gap <= 1e-4 and qc == hc and qh == hh
print(f"QEMU against host cc: {len(qu)} commands, {same} bit-equal, largest difference "
      f"{gap:.3g} of the scale (bound 1e-4); {' '.join(qc)} (host: {' '.join(hc)}); "
      f"{' '.join(qh)} (host: {' '.join(hh)}): {'agree' if ok else 'DIFFER'}")
if os.path.exists(sys.argv[3]):  # --model composed: the float64 torch compensator
    tu = [float(line.split()[1]) for line in open(sys.argv[3]) if line.strip()]
    assert len(tu) == len(qu), (len(tu), len(qu))
    tscale = max(1.0, max(abs(v) for v in tu))
    tgap = max(abs(a - b) for a, b in zip(qu, tu)) / tscale
    tok = tgap <= 1e-4
    print(f"QEMU against torch float64: {len(qu)} commands, largest difference {tgap:.3g} of "
          f"the scale (bound 1e-4): {'agree' if tok else 'DIFFER'}")
    ok = ok and tok
sys.exit(0 if ok else 1)
PYEOF
