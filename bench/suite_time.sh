#!/usr/bin/env bash
# Time the README's test command (the pytest part, in the existing .venv) with --durations, and keep the figures.
#   bash bench/suite_time.sh warm|cold
# warm: Taichi's offline cache as it is (a machine that has run the suite before; CI's runners may be such);
# cold: an empty cache (TI_OFFLINE_CACHE_FILE_PATH set to a fresh temporary folder), every kernel compiled.
# Writes bench/results/test_durations_<mode>_cpu.txt: a header (date, commit, cores, mode), the summary line and
# the 40 slowest items.
set -euo pipefail
cd "$(dirname "$0")/.."
mode="${1:-warm}"
case "$mode" in
  warm) ;;
  cold) export TI_OFFLINE_CACHE_FILE_PATH="$(mktemp -d)" ;;
  *) echo "usage: bash bench/suite_time.sh warm|cold" >&2; exit 2 ;;
esac
out="bench/results/test_durations_${mode}_cpu.txt"
# the tests start the command line in subprocesses, which import the installed package: install this tree first
.venv/bin/pip install -q --no-deps .
log="$(mktemp)"
start=$(date +%s)
set +e
.venv/bin/python -m pytest -q -n 2 --dist loadfile --durations=40 tests >"$log" 2>&1
rc=$?
set -e
end=$(date +%s)
{
  echo "pytest -q -n 2 --dist loadfile --durations=40 tests ($mode Taichi cache), $(date -u +%F), commit $(git rev-parse --short HEAD), $(nproc) cores: exit $rc, $((end - start)) s wall"
  grep -E "^[0-9]+ (passed|failed)|passed|failed" "$log" | tail -1
  sed -n '/slowest 40 durations/,/^$/p' "$log"
  grep -E "^FAILED" "$log" || true
} >"$out"
cat "$out"
rm -f "$log"
exit $rc
