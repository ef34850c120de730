#!/usr/bin/env bash
# What a lent GPU (the device tool) needs beside the tracked tree to run scripts/gpu_check.sh: made here in
# one command, taken there in a few calls, so that a session's 15 device minutes go to the checks.
#
# Here:   bash scripts/gpu_carry.sh pack
#   Downloads the cp312 wheels of warp-lang, embreex, trimesh and roma (the device image lacks them; PyPI),
#   unpacks them without Warp's examples, tests and CPU compiler (warp/native stays: CUDA kernels compile
#   from its headers), adds anny's Python package (without the data only its cache build reads) and the one
#   anny cache file uvatar loads, packs it all as one xz tarball split into .carry/p1, p2, ... (each small
#   enough to travel with the tree under the 64 MiB a call), and moves the viewer's onnxruntime wasm (24 MB)
#   and docs/ (12 MB of pictures) aside into .carry-aside/ so the tree travels at ~5 MB
#   (`bash scripts/gpu_carry.sh restore` puts them back). .carry/ and .carry-aside/ are git-ignored
#   through .git/info/exclude. It prints the device calls to make.
# There, one call per part, each within 30 s of the last (the machine stays warm that long; /tmp survives):
#   run(command="bash scripts/gpu_carry.sh store", carry=[".carry/p1"], timeout_s=60)            # p1 .. p(n-1)
#   run(command="bash scripts/gpu_carry.sh store && $CHECK", carry=[".carry/pN"], timeout_s=560)  # the last part
#   with CHECK (below): the open bar of issue 39 first (the nearest-sample search's lanes as the bake asks it,
#   the frames' refinements in flight, the bake with its profile, 4 workers and the refinement's graph, one process
#   writing behind, the refinement's posing twin against Warp), then the CUDA tests, the training
#   step (eager and replayed from its graph) and the CPU bake on the machine's cores (the GPU bake's baseline), within one call (BUDGET 520 s) that a
#   fresh 15-minute lease allows after the machine's start (~40 s; with less left, lower BUDGET and the parts'
#   seconds: session 13 fitted 355 s). Results: one results.tgz (status.txt beside it).
#   `store` keeps the part in /tmp/uvatar_carry; `check PARTS` unpacks all parts into /tmp/site (the anny
#   cache into ~/.cache/anny/v14), exports PYTHONPATH and runs scripts/gpu_check.sh PARTS (its env.txt says
#   what imports). While the machine is warm, later calls need only `bash scripts/gpu_carry.sh check ...`.
set -euo pipefail
cd "$(dirname "$0")/.."
PART_MB=${PART_MB:-56}
CHECK="BUDGET=520 BAKE_LANES=auto BAKE_WORKERS=4,8 BAKE_GRAPH_WORKERS=4 BAKE_MPS_WORKERS=4,8 BAKE_MPS_GRAPH=1 BAKE_THROUGHPUT_FRAMES=32 BAKE_IN_FLIGHT=4 NEAREST_SECONDS=20 FLIGHT_SECONDS=70 BAKE_SECONDS=140 BAKE_GRAPH_SECONDS=30 BAKE_MPS_SECONDS=40 WRITE_SECONDS=40 POSE_SECONDS=15 TESTS_SECONDS=80 BAKE_CPU_SECONDS=45 TRAIN_COMPILE=off,off+cl+graph TRAIN_SECONDS=40 bash scripts/gpu_carry.sh check nearest flight bake write pose tests bake_cpu train"
STORE=/tmp/uvatar_carry

pack() {
  local stage=.carry/stage wheels=.carry/wheels
  grep -qx '/.carry/' .git/info/exclude 2>/dev/null || echo '/.carry/' >> .git/info/exclude
  grep -qx '/.carry-aside/' .git/info/exclude 2>/dev/null || echo '/.carry-aside/' >> .git/info/exclude
  rm -rf .carry && mkdir -p "$stage/site" "$stage/anny_cache" "$wheels"
  local plats=() n
  for n in 28 27 17; do plats+=(--platform "manylinux_2_${n}_x86_64"); done
  python3 -m pip download -q --no-deps --only-binary=:all: --python-version 3.12 --implementation cp \
    "${plats[@]}" --platform manylinux2014_x86_64 -d "$wheels" \
    warp-lang==1.19.0 embreex==4.4.0.post1 trimesh==5.2.0 roma==1.8.0
  for w in "$wheels"/*.whl; do python3 -m zipfile -e "$w" "$stage/site"; done
  rm -rf "$stage/site/warp/examples" "$stage/site/warp/tests" "$stage/site/warp/bin/warp-clang.so"
  local anny_dir cache
  anny_dir=$(python3 -c "import anny, os; print(os.path.dirname(anny.__file__))")
  (cd "$(dirname "$anny_dir")" && tar cf - --exclude=__pycache__ --exclude=anny/data/mpfb2 --exclude=anny/data/soma \
     --exclude=anny/data/cached --exclude=anny/examples anny) | tar xf - -C "$stage/site"
  # its metadata too: anny reads its own version through importlib.metadata (without it, `import anny`
  # fails there; session 10 lost a device call to that)
  local meta
  meta=$(python3 -c "import importlib.metadata as m; print(m.distribution('anny')._path)")
  cp -r "$meta" "$stage/site/"
  cache=$(ls "$HOME"/.cache/anny/v14/build_compact_model_data_*.safetensors 2>/dev/null | head -1 || true)
  if [ -z "$cache" ]; then   # anny builds its cache on first use (~1 min)
    python3 -c "from uvatar.body import load_body_model; load_body_model('anny')" >/dev/null
    cache=$(ls "$HOME"/.cache/anny/v14/build_compact_model_data_*.safetensors | head -1)
  fi
  cp "$cache" "$stage/anny_cache/"
  tar cf - -C "$stage" site anny_cache | xz -T0 -6 | split -b "${PART_MB}m" -a 1 --numeric-suffixes=1 - .carry/p
  rm -rf "$stage" "$wheels"
  mkdir -p .carry-aside
  local wasm=src/uvatar/viewer/static/ort/ort-wasm-simd-threaded.jsep.wasm
  [ -f "$wasm" ] && mv "$wasm" .carry-aside/
  if [ -d docs ]; then
    [ -e .carry-aside/docs ] && { echo "pack: .carry-aside/docs exists (restore first)"; exit 2; }
    mv docs .carry-aside/
  fi
  local parts=(.carry/p*) last
  last=${parts[-1]}
  ls -l .carry/
  echo "tree that travels: $(git ls-files -z | xargs -0 du -cb 2>/dev/null | tail -1 | cut -f1) bytes (tracked, present)"
  echo "device calls, each within 30 s of the last:"
  for p in "${parts[@]}"; do
    if [ "$p" = "$last" ]; then
      echo "  run(command=\"bash scripts/gpu_carry.sh store && $CHECK\", carry=[\"$p\"], timeout_s=560)"
    else
      echo "  run(command=\"bash scripts/gpu_carry.sh store\", carry=[\"$p\"], timeout_s=60)"
    fi
  done
  echo "afterwards: bash scripts/gpu_carry.sh restore"
}

store() {  # keep the carried part(s) in /tmp for the calls that follow
  mkdir -p "$STORE"
  local p found=0
  for p in .carry/p*; do [ -f "$p" ] && cp "$p" "$STORE/" && found=1; done
  [ "$found" = 1 ] || { echo "store: no .carry/p* travelled with this call (name it in carry)"; exit 2; }
  ls -l "$STORE"
}

unpack() {  # all parts -> /tmp/site and the anny cache
  [ -d /tmp/site/warp ] && return 0
  ls "$STORE"/p* >/dev/null 2>&1 || { echo "unpack: no parts in $STORE (store them first)"; exit 2; }
  mkdir -p /tmp/site_unpack "$HOME/.cache/anny/v14"
  cat "$STORE"/p* | xz -d | tar xf - -C /tmp/site_unpack
  mv /tmp/site_unpack/anny_cache/*.safetensors "$HOME/.cache/anny/v14/"
  mv /tmp/site_unpack/site /tmp/site
  rm -rf /tmp/site_unpack
}

case ${1:-} in
  pack) pack ;;
  store) store ;;
  check) shift; t0=$SECONDS; unpack
         # the checks' budget: what is left of a 560 s call after the unpacking, less 20 s for the files' return
         export BUDGET=${BUDGET:-$((540 - (SECONDS - t0)))} PYTHONPATH=/tmp/site${PYTHONPATH:+:$PYTHONPATH}
         exec bash scripts/gpu_check.sh "$@" ;;
  restore) [ -f .carry-aside/ort-wasm-simd-threaded.jsep.wasm ] && mv .carry-aside/ort-wasm-simd-threaded.jsep.wasm src/uvatar/viewer/static/ort/
           [ -d .carry-aside/docs ] && [ ! -e docs ] && mv .carry-aside/docs docs
           git status --short | head ;;
  *) echo "usage: bash scripts/gpu_carry.sh pack | store | check PARTS... | restore (see the header)"; exit 2 ;;
esac
