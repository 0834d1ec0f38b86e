#!/usr/bin/env bash
# Run the test suite N times in a row and count the failing runs (flaky tests show up here).
#   bench/repeat_suite.sh [N] [pytest args...]      e.g. bench/repeat_suite.sh 20 tests/test_can_bus.py
set -u
cd "$(dirname "$0")/.."
n=${1:-20}
shift || true
failed=0
logs=$(mktemp -d -t repeat-suite-XXXX)
for i in $(seq 1 "$n"); do
  if .venv/bin/python -m pytest -q -p no:cacheprovider "$@" > "$logs/$i.log" 2>&1; then
    echo "run $i: ok ($(tail -n 1 "$logs/$i.log"))"
  else
    failed=$((failed + 1))
    echo "run $i: FAILED, see $logs/$i.log"
  fi
done
echo "$((n - failed)) passed, $failed failed"
[ "$failed" -eq 0 ]
