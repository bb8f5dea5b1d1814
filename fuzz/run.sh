#!/usr/bin/env bash
# Runs every fuzz target of this crate with cargo-fuzz (nightly toolchain):
#   fuzz/run.sh [SECONDS]      each target for SECONDS (default 10): what .ci/run does
#   fuzz/run.sh --runs N       each target for N executions (the 10 M runs quoted in README)
# Seeds are in fuzz/seeds/<target> (committed); the growing corpus in fuzz/corpus/<target> and
# crashes in fuzz/artifacts/<target> are not. Prints each target's execution count; exits 1 on
# the first crash.
set -euo pipefail
cd "$(dirname "$0")"
limit=(-max_total_time="${1:-10}")
if [ "${1:-}" = --runs ]; then
    limit=(-runs="${2:?--runs needs a number}")
fi
mkdir -p logs
for target in $(cargo +nightly fuzz list); do
    mkdir -p "corpus/$target" "seeds/$target"
    start=$(date +%s)
    if ! cargo +nightly fuzz run "$target" "corpus/$target" "seeds/$target" -- \
        "${limit[@]}" -print_final_stats=1 >"logs/$target.log" 2>&1; then
        echo "fuzz target $target FAILED (see fuzz/logs/$target.log, fuzz/artifacts/$target)" >&2
        tail -n 30 "logs/$target.log" >&2
        exit 1
    fi
    runs=$(grep -o 'stat::number_of_executed_units: *[0-9]*' "logs/$target.log" | grep -o '[0-9]*$' || echo "?")
    echo "fuzz $target: $runs executions in $(( $(date +%s) - start )) s, no crash"
done
