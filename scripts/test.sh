#!/usr/bin/env bash
# The README's test command: install uvatar with its test extras, then run pytest.
# pytest's exit code 5 ("no tests collected") is treated as a failure on purpose: a suite that
# collects nothing is broken.
set -euo pipefail
cd "$(dirname "$0")/.."
python -m pip install --quiet torch==2.13.0
python -m pip install --quiet -e ".[test]"
if command -v apt-get >/dev/null 2>&1 && ! command -v chromium >/dev/null 2>&1; then
  if [ "$(id -u)" = "0" ]; then
    (apt-get update -qq && apt-get install -y -qq chromium >/dev/null) || echo "chromium not installed: browser tests will skip"
  fi
fi
python -m pytest -q -m "not gpu" --timeout=900 "$@"
