#!/usr/bin/env bash
# The GPU figures of issue 39 in one call on a lent GPU (the device tool), most important first:
#   run(command="bash scripts/gpu_check.sh", timeout_s=600)          # dva avh tests bake, within $BUDGET s (560)
#   run(command="bash scripts/gpu_check.sh avh tests", timeout_s=300) # some parts: dva avh tests compile bake train
#   run(command="bash scripts/gpu_check.sh bake tests", timeout_s=420) # the GPU bake (issue 39 item 3) and the tests
# (nearest: the nearest-sample kernel against the k-d tree; rays: Warp's BVH builds on the bake's rays; compile: compiled against eager on the machine's
# CPU, which CI's machine can do too; bake: the CUDA bake (with --profile: each stage's device time),
# which needs anny carried as well; train: bench/dva_train.py's paper-scale step, synchronised and pipelined)
# Env overrides: BUDGET (s), DVA_PATHS / DVA_REPEATS / DVA_PAIRS (bench/dva_frame.py's --paths, --repeats,
# --pairs-per-ray: the marcher's fixed pair buffer per ray), AVH_SECONDS / AVH_FAST / AVH_MODES / AVH_ITERS,
# TRAIN_STEPS, TRAIN_SECONDS, TRAIN_POSE (bench/dva_train.py's --pose, default "auto": the pose-corrected step
# with the body re-posed on the GPU; "auto,host" adds the CPU re-posing as before), TRAIN_COMPILE (its --compile,
# default "off,off+cl+graph,default+cl,default+cl+graph": the eager step, the whole step replayed from a CUDA
# graph, then compiled, with and without the graph), BAKE_SECONDS /
# BAKE_FRAMES / BAKE_WORKERS (default 4,8: a throughput run each) / BAKE_THROUGHPUT_FRAMES (the frames each run bakes, default 32),
# TRAIN_CROPS (bench/dva_train.py --crops: batch, the one marcher call, and/or each, the per-sample reference),
# BAKE_BVH (bench/bake.py --bvh, e.g. lbvh:4: the Warp meshes' BVH, after the rays part has compared them), TESTS_SECONDS,
# BAKE_IN_FLIGHT (bench/bake.py --frames-in-flight, default 4), FLIGHT_SECONDS / FLIGHT_FRAMES / FLIGHT_COUNTS /
# FLIGHT_REPEATS (the flight part: bench/bake_in_flight.py), BAKE_CPU_SECONDS / BAKE_CPU_WORKERS / BAKE_CPU_FRAMES
# (the bake_cpu part: the CPU bake on the machine's cores, the GPU bake's baseline), WRITE_SECONDS / WRITE_FRAMES /
# WRITE_REPEATS (the write part: bench/bake_overlap.py --synthetic, a one-process bake writing behind, reading ahead),
# POSE_SECONDS (the pose part: bench/body_pose.py --quick, the refinement's posing by the twin and in Warp).
# Issue 39's sync-free frame: the dva
# part's paths "+exact" (the old read-back per frame), plain (no read-back), "+graph" (the whole driven frame in one CUDA graph); each row has
# <path>_drive_render_ms (synchronised per frame), <path>_drive_render_pipelined_ms (back to back),
# <path>_drive_psnr_vs_ref, <path>_pairs_per_ray_peak and <path>_pair_overflows; the training rows
# train_<p>_step_ms and train_<p>_pipelined_step_ms.
# Writes $OUT/results.tgz (the device tool's output folder; ./gpu_out elsewhere), packed after every part:
# env.txt (card, versions, which packages import), <part>.json (a bench's stdout) with <part>.log (its
# stderr, one line per finished row, so a cut run still tells), pytest_*.txt, trace.txt, and status.txt
# (each part's exit code; 124 = it ran past its time; also beside the tarball). BAKE_LANES (a number, or
# auto: the nearest part's fastest) sets bench/bake.py --nearest-lanes; BAKE_GRAPH_WORKERS the refinement
# graph's throughput run; BAKE_MPS_WORKERS (e.g. 4,8) a throughput run under CUDA MPS (BAKE_MPS_GRAPH=1: with
# the refinement's graph), where the machine has the MPS control daemon. Each part gets the smaller of its own limit and what is left of $BUDGET.
# A bare device machine lacks uvatar's compiled dependencies: carry Warp (the fused marcher, the device
# unwrap), embreex (the toy capture, the reference unwrap) and anny (the bake) as docs/DESIGN notes say;
# env.txt lists what imports. Without Warp the marcher falls back to its torch twin (JSON "marcher").
# Carrying: `bash scripts/gpu_carry.sh pack` (here) makes .carry/p1, p2 (the cp312 wheels of warp-lang, embreex,
# trimesh and roma, anny's package and its cache file; ~115 MB in two parts), moves the viewer's 24 MB ort wasm
# and docs/ aside so the tree travels at ~5 MB, and prints the two device calls: the first stores p1 in /tmp,
# the second (within the 30 s the machine stays warm) brings p2, unpacks both into /tmp/site and runs this
# script (`bash scripts/gpu_carry.sh check train bake tests`, with the parts' times its header gives).
# `bash scripts/gpu_carry.sh restore` afterwards. When the training step's CUDA graph capture fails (the
# JSON's graph_error), `python scripts/gpu_trace_capture.py` there names the operation after which the
# capture broke and tries the capture modes.
set -uo pipefail
cd "$(dirname "$0")/.."
# the device tool brings back only a few files: every part writes into a work folder, packed after each
# part into one $OUT/results.tgz (and status.txt beside it), so a cut run still returns what it finished
FINAL=${OUT:-$PWD/gpu_out}
OUT=$(mktemp -d /tmp/gpu_check.XXXX)
mkdir -p "$FINAL"
pack_results() { tar czf "$FINAL/results.tgz.part" -C "$OUT" . && mv "$FINAL/results.tgz.part" "$FINAL/results.tgz"
                 cp "$OUT/status.txt" "$FINAL/status.txt" 2>/dev/null || true; }
export PYTHONPATH=$PWD/src:$PWD${PYTHONPATH:+:$PYTHONPATH} UVATAR_COMPILE_TESTS=1 PYTHONUNBUFFERED=1
DEADLINE=$((SECONDS + ${BUDGET:-560}))
PARTS=${*:-dva avh tests bake}

limit() {  # limit SECONDS: the smaller of SECONDS and what is left of the budget
  local left=$((DEADLINE - SECONDS))
  echo $(( $1 < left ? $1 : left ))
}
run_part() {  # run_part NAME SECONDS OUTFILE COMMAND...
  local name=$1 want=$2 out=$3; shift 3
  local t0=$SECONDS s
  s=$(limit "$want")
  if [ "$s" -le 5 ]; then echo "$name skipped: no time left" | tee -a "$OUT/status.txt"; return; fi
  timeout --kill-after=10 "$s" "$@" > "$out" 2> "$OUT/$name.log"
  echo "$name rc=$? limit=${s}s took=$((SECONDS - t0))s" | tee -a "$OUT/status.txt"
  pack_results
}

{
  nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv,noheader || echo "no nvidia-smi"
  python - <<'EOF'
import importlib.util, torch
print("torch", torch.__version__, "cuda", torch.version.cuda, "available", torch.cuda.is_available())
for m in ("warp", "embreex", "anny", "onnxruntime", "roma", "trimesh", "scipy", "cv2"):
    print(m, "yes" if importlib.util.find_spec(m) else "MISSING")
EOF
} > "$OUT/env.txt" 2>&1
cat "$OUT/env.txt"

for part in $PARTS; do
  case $part in
    dva)  # the DVA frame at 1024², paper preset (K = 4096, S = 16): training steps fp32 / bf16, then per
          # path drive + render with its PSNR against the fp32 reference (<= 16 ms at >= 40 dB; step <= 80 ms)
      run_part dva 330 "$OUT/dva_frame.json" python bench/dva_frame.py --device cuda --warmup 3 --steps 10 \
        --repeats "${DVA_REPEATS:-10}" --profile ${DVA_PAIRS:+--pairs-per-ray "$DVA_PAIRS"} \
        --paths "${DVA_PATHS:-fp32+exact,fp32,fp16+cl,fp16+cl+graph,bf16+cl+graph,bf16+compile+cl+graph}" ;;
    avh)  # the AVH generator, paper preset at 1024²: batch 1 fps, batch-8 maps/s, bf16 / fp16, eager and
          # compiled with CUDA graphs (>= 500 fps)
      run_part avh "${AVH_SECONDS:-110}" "$OUT/avh_fast.json" python bench/avh.py --device cuda --presets fc32-l1024 \
        --resolutions 1024 --no-train --no-onnx --fast "${AVH_FAST:-bf16,fp16}" \
        --compile-modes "${AVH_MODES:-reduce-overhead}" --iters "${AVH_ITERS:-30}" ;;
    tests)  # the CUDA parity tests: fast paths against their fp32 twins, the device unwrap, the marcher, a
            # driven frame under sync debug mode "error" and replayed from its CUDA graph, the bake's torch stages
      run_part tests "${TESTS_SECONDS:-180}" "$OUT/pytest_gpu.txt" python -m pytest -q -m gpu -p no:cacheprovider \
        tests/test_dva_frame.py tests/test_avh_inference.py tests/test_dva_unwrap_device.py tests/test_dva_raymarch_warp.py \
        tests/test_dva_frame_sync.py tests/test_dva_train_posing.py tests/test_dva_train_compile.py tests/test_dva_tv_warp.py \
        tests/test_dva_train_graph.py tests/test_dva_raymarch_crops.py tests/test_avh_bake_register_device.py tests/test_avh_bake_refine_device.py \
        tests/test_avh_bake_refine_graph.py tests/test_geometry_raycast_warp.py tests/test_geometry_banded_solve.py tests/test_avh_bake_refine_step_warp.py \
        tests/test_devices.py tests/test_geometry_nearest_warp.py tests/test_geometry_jump_flood_warp.py \
        tests/test_body_anny.py::test_cuda_pose_with_a_host_shape_reads_nothing_back tests/test_avh_bake_torch.py \
        tests/test_avh_bake_speed.py::test_cuda_bake_matches_the_cpu_bake tests/test_avh_bake_refine_in_flight.py \
        tests/test_avh_bake_stencil_warp.py tests/test_body_pose_warp.py ;;
    train)  # the paper preset's training step (K = 4096, S = 16): synchronised and pipelined (<= 80 ms)
      # (--compile: the step's encoders and decoders eager, then through torch.compile; compiled in the warm-up)
      run_part train "${TRAIN_SECONDS:-300}" "$OUT/dva_train.json" python bench/dva_train.py --device cuda --preset paper \
        --grids 64 --voxels 16 --marchers warp --warmup 3 --steps "${TRAIN_STEPS:-20}" --profile --count-ops \
        --crops "${TRAIN_CROPS:-batch}" \
        ${DVA_PAIRS:+--pairs-per-ray "$DVA_PAIRS"} --pose "${TRAIN_POSE:-auto}" --compile "${TRAIN_COMPILE:-off,off+cl+graph,default+cl,default+cl+graph}" ;;
    nearest)  # the nearest-sample kernel (the grid, session 10) against SciPy's k-d tree, on the GPU, as the
              # bake's refinement asks it (4,000 queries 10-50 mm off ~165k samples, within 94 mm), with 1 to 32
              # threads per query (session 13's lanes; BAKE_LANES=auto takes the fastest for the bake)
      run_part nearest "${NEAREST_SECONDS:-60}" "$OUT/nearest.json" python bench/nearest.py --device cuda --no-slab \
        --samples 165000 --queries 4000 --offset-mm 10,50 --limit 0.094 --lanes 1,4,8,16,32 ;;
    trace)  # why the training step's CUDA graph capture fails (scripts/gpu_trace_capture.py): traced, then
            # untraced in two modes, then slowed by a pass-through dispatch mode only
      run_part trace "${TRACE_SECONDS:-90}" "$OUT/trace.txt" python scripts/gpu_trace_capture.py \
        --modes "${TRACE_MODES:-global,thread_local,relaxed,relaxed+null}" ;;
    rays)  # Warp's BVH constructors and leaf sizes on the bake's ray patterns (the default LBVH ran the bake's
           # first hits at ~65 M rays/s on the H200; on the CPU a leaf of 4 casts 1.7-2x faster than 1)
      run_part rays "${RAYS_SECONDS:-45}" "$OUT/raycast_bvh.json" python bench/raycast_bvh.py --device cuda \
        --rays "${RAYS:-1000000}" --leaf-sizes 1,2,4,8 --repeats 3 ;;
    compile)  # compiled against eager (torch.compile on the machine's CPU cores; ~130 s on 2 cores)
      run_part compile 90 "$OUT/pytest_compile.txt" python -m pytest -q -x -p no:cacheprovider -k compiled \
        tests/test_dva_frame.py tests/test_avh_inference.py tests/test_dva_train_compile.py ;;
    bake)  # the bake on CUDA (needs anny and Warp): its rays through Warp and the stages that cast no rays
           # on torch (<= 0.3 s per frame with the colour rounds), with --parity: the same frames again with
           # those stages on the CPU (torch_stages off), and how far the maps and poses moved (eval unchanged:
           # |delta x| median < 0.1 mm, texture PSNR within 0.2 dB)
      if python -c "import anny, warp" 2>/dev/null; then
        lanes=${BAKE_LANES:-}
        if [ "$lanes" = auto ]; then   # the fastest of the nearest part's lanes, if it ran
          lanes=$(python -c "import json; d=json.load(open('$OUT/nearest.json'))['grid_lanes_ms']; print(min(d, key=d.get))" 2>/dev/null || true)
          echo "bake: nearest lanes ${lanes:-default}" | tee -a "$OUT/status.txt"
        fi
        # --workers: the frames again on that many processes sharing the GPU (one frame's CPU work overlaps
        # another's GPU work): throughput.seconds_per_frame is the machine's wall time per frame
        # (4 and 8 of the machine's 16 cores); --count-ops: the torch operators and Warp launches per stage, the
        # host's launches (session 9 cut them about in half: the nearest samples in one Warp launch, doubling FK)
        # --frames-in-flight: the frames' refinements and colour rounds one at a time, then that many at a time
        # on their own CUDA streams (uvatar bake --frames-in-flight, session 14): in_flight.seconds_per_frame_with_colour_rounds
        run_part bake "${BAKE_SECONDS:-240}" "$OUT/bake.json" python bench/bake.py --device cuda --count-ops --profile \
          --frames "${BAKE_FRAMES:-4}" --parity --workers "${BAKE_WORKERS:-4,8}" --throughput-frames "${BAKE_THROUGHPUT_FRAMES:-32}" \
          --frames-in-flight "${BAKE_IN_FLIGHT:-4}" ${BAKE_BVH:+--bvh "$BAKE_BVH"} ${lanes:+--nearest-lanes "$lanes"}
        # the refinement's iterations replayed from one CUDA graph (PoseRefineConfig.cuda_graph, off by default
        # until measured): seconds per frame and parity beside the run above; refine_graph_failures if any
        run_part bake_graph "${BAKE_GRAPH_SECONDS:-90}" "$OUT/bake_graph.json" python bench/bake.py --device cuda \
          --frames 2 --parity --refine-cuda-graph ${BAKE_BVH:+--bvh "$BAKE_BVH"} ${lanes:+--nearest-lanes "$lanes"} \
          --workers "${BAKE_GRAPH_WORKERS:-1}" --throughput-frames "${BAKE_THROUGHPUT_FRAMES:-32}"
        # the workers' frames under CUDA MPS (BAKE_MPS_WORKERS, e.g. 4,8): without it the processes' kernels
        # take turns on the GPU, and a refinement's are small (a few thousand queries or rays a launch);
        # MPS runs them side by side. A user-space daemon, its pipes in /tmp, quit afterwards; the GPU's
        # settings (compute mode, MIG) are left as they are. Skipped where the machine has no MPS.
        if [ -n "${BAKE_MPS_WORKERS:-}" ]; then
          if command -v nvidia-cuda-mps-control >/dev/null; then
            export CUDA_MPS_PIPE_DIRECTORY=/tmp/mps_pipe CUDA_MPS_LOG_DIRECTORY=/tmp/mps_log
            mkdir -p "$CUDA_MPS_PIPE_DIRECTORY" "$CUDA_MPS_LOG_DIRECTORY"
            if nvidia-cuda-mps-control -d; then
              run_part bake_mps "${BAKE_MPS_SECONDS:-90}" "$OUT/bake_mps.json" python bench/bake.py --device cuda \
                --frames 1 --workers "$BAKE_MPS_WORKERS" --throughput-frames "${BAKE_THROUGHPUT_FRAMES:-32}" \
                ${BAKE_MPS_GRAPH:+--refine-cuda-graph} ${BAKE_BVH:+--bvh "$BAKE_BVH"} ${lanes:+--nearest-lanes "$lanes"}
              echo quit | nvidia-cuda-mps-control
              cp "$CUDA_MPS_LOG_DIRECTORY"/control.log "$OUT/mps_control.log" 2>/dev/null || true
            else
              echo "bake_mps skipped: the MPS daemon did not start" | tee -a "$OUT/status.txt"
            fi
            unset CUDA_MPS_PIPE_DIRECTORY CUDA_MPS_LOG_DIRECTORY
          else
            echo "bake_mps skipped: no nvidia-cuda-mps-control on this machine" | tee -a "$OUT/status.txt"
          fi
        fi
      else
        echo "bake skipped: anny or warp missing" | tee -a "$OUT/status.txt"
      fi ;;
    write)  # one process baking 4 frames (uvatar bake --workers 1) with each frame written on a thread while the
            # next bakes and the next scans read ahead, against writing behind only and against neither, in one
            # run (bench/bake_overlap.py): the GPU's idle time a frame's compression (~0.5 s at 1024²) and
            # scan read no longer add
      if python -c "import anny, warp" 2>/dev/null; then
        run_part write "${WRITE_SECONDS:-90}" "$OUT/bake_overlap.json" python bench/bake_overlap.py \
          --synthetic "${WRITE_FRAMES:-4}" --device cuda --texels 1024 --repeats "${WRITE_REPEATS:-1}"
      else
        echo "write skipped: anny or warp missing" | tee -a "$OUT/status.txt"
      fi ;;
    pose)  # anny posed as the bake's refinement poses it, by the torch twin and in three Warp launches
           # (session 16), in the same run (bench/body_pose.py's refine_pose_*), beside the batch posing rows
      if python -c "import anny, warp" 2>/dev/null; then
        run_part pose "${POSE_SECONDS:-30}" "$OUT/body_pose.json" python bench/body_pose.py --quick --device cuda
      else
        echo "pose skipped: anny or warp missing" | tee -a "$OUT/status.txt"
      fi ;;
    bake_cpu)  # the same machine's CPUs as the GPU bake's baseline: the CPU bake (Embree, numpy) on
               # BAKE_CPU_WORKERS processes (default 16), wall seconds per frame with the writes
      run_part bake_cpu "${BAKE_CPU_SECONDS:-90}" "$OUT/bake_cpu.json" python bench/bake.py --device cpu --frames 1 \
        --warmup 0 --workers "${BAKE_CPU_WORKERS:-16}" --throughput-frames "${BAKE_CPU_FRAMES:-32}" ;;
    flight)  # the refinements and colour rounds of 8 frames 1, 2, 4 and 8 at a time, each frame on its own CUDA
             # stream (bench/bake_in_flight.py): seconds per frame, the speed-up in the same run, identical fits
      if python -c "import anny, warp" 2>/dev/null; then
        run_part flight "${FLIGHT_SECONDS:-120}" "$OUT/bake_in_flight.json" python bench/bake_in_flight.py --device cuda \
          --frames "${FLIGHT_FRAMES:-8}" --in-flight "${FLIGHT_COUNTS:-1,2,4,8}" --repeats "${FLIGHT_REPEATS:-2}"
      else
        echo "flight skipped: anny or warp missing" | tee -a "$OUT/status.txt"
      fi ;;
    *) echo "unknown part $part (dva avh tests compile bake bake_cpu flight write pose train nearest rays trace)" | tee -a "$OUT/status.txt" ;;
  esac
done
tail -n 3 "$OUT"/pytest_*.txt 2>/dev/null
pack_results
