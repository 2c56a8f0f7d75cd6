#!/usr/bin/env bash
# The test suite as `make test` runs it (after setup): ruff, the suite on two workers, then the
# timing tests alone. Ends with a recap of every failed or errored test of both runs, so the last
# lines of the output (all a CI log may keep) name what failed. Exit status: non-zero if any failed.
set -uo pipefail
cd "$(dirname "${BASH_SOURCE[0]}")/.."

ruff check . || exit $?

logs=$(mktemp -d)
trap 'rm -rf "$logs"' EXIT

python -m pytest -n 2 -m "not timing" "$@" 2>&1 | tee "$logs/suite.log"
suite=${PIPESTATUS[0]}
python -m pytest -m timing "$@" 2>&1 | tee "$logs/timing.log"
timing=${PIPESTATUS[0]}

echo
echo "== make test: suite exit ${suite}, timing tests exit ${timing}"
for run in suite timing; do
    grep -E '^(FAILED|ERROR) ' "$logs/$run.log" | sed "s/^/[$run] /"
    grep -E '^=+ .*(passed|failed|error).* in [0-9.]+s' "$logs/$run.log" | tail -1 | sed "s/^/[$run] /"
done
if [ "$suite" -ne 0 ]; then exit "$suite"; fi
exit "$timing"
