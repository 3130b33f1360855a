#!/usr/bin/env bash
# Time the README's test command (the pytest part, in the .venv the README's test command made) with --durations,
# and keep the figures.
#   bash bench/suite_time.sh warm|cold
# warm: Taichi's offline cache as it is (a machine that has run the suite before);
# cold: an empty cache (TI_OFFLINE_CACHE_FILE_PATH set to a fresh temporary folder), every kernel compiled.
# The tests start the command line in subprocesses, which import the installed package, so this tree is installed
# into .venv first (pip install --no-deps .). Writes bench/results/test_durations_<mode>_cpu.txt: a header (date,
# commit, cores, mode, exit status, wall time), pytest's summary line, the 40 slowest items and any FAILED lines;
# with `cold`, also tests/file_seconds.json (each file's seconds: the suite queues its files heaviest first by it,
# tests/conftest.py). pytest's whole output (the failures' tracebacks) is kept in out/suite_time_<mode>.log.
set -euo pipefail
cd "$(dirname "$0")/.."
mode="${1:-warm}"
if [ ! -x .venv/bin/python ]; then
  echo "no .venv here: run the README's test command first (it creates .venv and installs the test extras)" >&2
  exit 2
fi
tmp="$(mktemp -d)"
trap 'rm -rf "$tmp"' EXIT
case "$mode" in
  warm) ;;
  cold) export TI_OFFLINE_CACHE_FILE_PATH="$tmp/taichi_cache" ;;
  *) echo "usage: bash bench/suite_time.sh warm|cold" >&2; exit 2 ;;
esac
out="bench/results/test_durations_${mode}_cpu.txt"
log="$tmp/pytest.log"
.venv/bin/pip install -q --no-deps .
start=$(date +%s)
set +e
record=()
[ "$mode" = cold ] && record=(--record-file-seconds)
.venv/bin/python -m pytest -q -n 2 --dist loadfile --durations=40 "${record[@]}" tests >"$log" 2>&1
rc=$?
set -e
end=$(date +%s)
{
  echo "pytest -q -n 2 --dist loadfile --durations=40 tests ($mode Taichi cache), $(date -u +%F), commit $(git describe --always --dirty), $(nproc) cores: exit $rc, $((end - start)) s wall"
  grep -E "(passed|failed|error)" "$log" | grep -E " in [0-9.]+s" | tail -1 || true
  grep -E "slowest 40 durations|^[0-9.]+s (setup|call|teardown) " "$log" || true
  grep -E "^(FAILED|ERROR)" "$log" || true
} >"$out"
cat "$out"
# the whole pytest output (the failures' tracebacks), which the temporary folder would take with it
mkdir -p out
cp "$log" "out/suite_time_${mode}.log"
echo "pytest's output: out/suite_time_${mode}.log"
exit $rc
