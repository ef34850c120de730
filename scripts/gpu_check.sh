#!/usr/bin/env bash
# The GPU figures of issue 39 in one call on a lent GPU (the device tool), most important first:
#   run(command="bash scripts/gpu_check.sh", timeout_s=600)
# Writes into $OUT (the device tool's output folder; ./gpu_out elsewhere): env.txt (card, versions,
# which optional packages import), one <name>.json per bench (stdout) with <name>.log (stderr), pytest_gpu.txt,
# and status.txt (each step's exit code; 124 = it ran past its share of the time). Each step has its own
# time limit so a slow one cannot starve the rest; the whole script stays under ~9 minutes.
# Warp and anny are not on a bare device machine: carry them as docs/DESIGN notes say. Without Warp the
# DVA marcher falls back to the torch twin (bench JSON "marcher": "torch") and the frame is slower;
# without anny the bake bench is skipped.
set -uo pipefail
cd "$(dirname "$0")/.."
OUT=${OUT:-$PWD/gpu_out}
mkdir -p "$OUT"
export PYTHONPATH=$PWD/src:$PWD UVATAR_COMPILE_TESTS=1 PYTHONUNBUFFERED=1
step() {  # step NAME SECONDS COMMAND...: stdout to NAME.json, stderr to NAME.log
  local name=$1 limit=$2; shift 2
  local t0=$SECONDS
  timeout --kill-after=10 "$limit" "$@" > "$OUT/$name.json" 2> "$OUT/$name.log"
  echo "$name rc=$? ${limit}s-limit took=$((SECONDS - t0))s" | tee -a "$OUT/status.txt"
}

{
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || echo "no nvidia-smi"
  python - <<'EOF'
import importlib.util, torch
print("torch", torch.__version__, "cuda", torch.version.cuda, "available", torch.cuda.is_available())
for m in ("warp", "anny", "embreex", "onnxruntime", "roma", "trimesh"):
    print(m, "yes" if importlib.util.find_spec(m) else "MISSING")
EOF
} > "$OUT/env.txt" 2>&1
cat "$OUT/env.txt"

# 1. the DVA frame at 1024², paper preset (K = 4096, S = 16): training steps fp32 / bf16, then drive +
#    render per path with its PSNR against the fp32 reference (targets: <= 16 ms at >= 40 dB; step <= 80 ms)
step dva_frame 270 python bench/dva_frame.py --device cuda --warmup 3 --steps 10 --repeats 10
# 2. the AVH generator, paper preset at 1024²: batch 1 fps and batch-8 maps/s, bf16 / fp16, eager and
#    compiled with CUDA graphs (target >= 500 fps)
step avh_fast 150 python bench/avh.py --device cuda --presets fc32-l1024 --resolutions 1024 --no-train \
  --no-onnx --fast bf16,fp16 --iters 30
# 3. the CUDA parity tests (fast paths against their fp32 twins; compiled against eager)
t0=$SECONDS
timeout --kill-after=10 120 python -m pytest -q -m gpu -x -p no:cacheprovider \
  tests/test_dva_frame.py tests/test_avh_inference.py tests/test_dva_unwrap_device.py tests/test_dva_raymarch_warp.py > "$OUT/pytest_gpu.txt" 2>&1
echo "pytest_gpu rc=$? took=$((SECONDS - t0))s" | tee -a "$OUT/status.txt"
# 4. compiled against eager (torch.compile on the machine's CPU cores; ~130 s on 2 cores)
t0=$SECONDS
timeout --kill-after=10 150 python -m pytest -q -x -p no:cacheprovider -k compiled \
  tests/test_dva_frame.py tests/test_avh_inference.py > "$OUT/pytest_compile.txt" 2>&1
echo "pytest_compile rc=$? took=$((SECONDS - t0))s" | tee -a "$OUT/status.txt"
# 5. the bake (needs anny and Warp)
if python -c "import anny, warp" 2>/dev/null; then
  step bake 60 python bench/bake.py --device cuda --frames 2
else
  echo "bake skipped: anny or warp missing" | tee -a "$OUT/status.txt"
fi
tail -n 3 "$OUT/pytest_gpu.txt"
