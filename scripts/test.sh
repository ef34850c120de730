#!/usr/bin/env bash
# The README's test command: install uvatar with its test extras, then run pytest.
# pytest's exit code 5 ("no tests collected") is treated as a failure on purpose: a suite that
# collects nothing is broken. Chromium (Debian) is installed for the browser tests when running as
# root; where it cannot be installed those tests skip with the reason.
set -euo pipefail
cd "$(dirname "$0")/.."
export PLAYWRIGHT_SKIP_BROWSER_DOWNLOAD=1   # the system chromium is used; playwright never downloads one
export DEBIAN_FRONTEND=noninteractive       # CI has no stdin: apt must never prompt

phase_start=$SECONDS
phase() { echo "[test.sh] $1: $((SECONDS - phase_start)) s" >&2; phase_start=$SECONDS; }

python -m pip install --quiet torch==2.13.0
python -m pip install --quiet -e ".[test,fit,cluster,kernels,formats,volumetric]"   # fit: the real BlazePose detector; cluster: Ray; kernels: Warp; formats: FBX/glTF motions; volumetric: Draco/KTX2
phase "install"

if command -v apt-get >/dev/null 2>&1 && ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = "0" ]; then
    (apt-get update -qq && apt-get install -y -qq chromium >/dev/null) || echo "chromium not installed: browser tests will skip" >&2
  fi
fi
phase "chromium"

status=0
python -m pytest -q -m "not gpu" --timeout=600 "$@" || status=$?
phase "tests"
if [ "$status" = "5" ]; then
  echo "[test.sh] pytest collected no tests: failing on purpose" >&2
fi
exit "$status"
