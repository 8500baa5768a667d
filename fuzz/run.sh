#!/usr/bin/env bash
# Runs every fuzz target for a while, one after the other, single job, and
# prints a summary: executions, coverage, corpus size and crashes per target.
#
# Usage: fuzz/run.sh [seconds-per-target] [target...]
#   default 300 s each, all targets. Seeds the corpora first (fuzz/seed.sh).
#
# cargo-fuzz needs nightly-only rustc flags (-Zsanitizer=address, sancov);
# with only a stable toolchain, RUSTC_BOOTSTRAP=1 lets stable rustc accept
# them. Crashes land in fuzz/artifacts/<target>/; replay one with
#   RUSTC_BOOTSTRAP=1 cargo fuzz run -O -a <target> fuzz/artifacts/<target>/crash-...
# and keep it in tests/fuzz_regressions.rs.
set -euo pipefail
cd "$(dirname "$0")/.."

seconds=${1:-300}
shift || true
targets=("$@")
if [ ${#targets[@]} -eq 0 ]; then
    # Every target there is: a list kept by hand missed three.
    for source in fuzz/fuzz_targets/*.rs; do
        targets+=("$(basename "$source" .rs)")
    done
fi

export RUSTC_BOOTSTRAP=1
if ! cargo fuzz --version >/dev/null 2>&1; then
    cargo install cargo-fuzz --locked
fi

fuzz/seed.sh
cargo fuzz build -O -a
mkdir -p fuzz/logs

summary=()
status=0
for target in "${targets[@]}"; do
    log=fuzz/logs/$target.log
    mkdir -p "fuzz/artifacts/$target" "fuzz/corpus/$target"
    before=$(find "fuzz/artifacts/$target" -type f | wc -l)
    echo "== $target: ${seconds}s (log: $log)"
    # One process, one thread: libFuzzer's default without -jobs/-workers
    # (-jobs=1 would fork a worker logging to ./fuzz-0.log instead). -a keeps
    # debug assertions and overflow checks on, as in the test suite.
    # -rss_limit_mb and -timeout turn memory blow-ups and hangs into findings.
    set +e
    cargo fuzz run -O -a "$target" "fuzz/corpus/$target" -- \
        -max_total_time="$seconds" -rss_limit_mb=2048 -timeout=10 \
        -print_final_stats=1 >"$log" 2>&1
    rc=$?
    set -e
    after=$(find "fuzz/artifacts/$target" -type f | wc -l)
    # The last status line: "#N  DONE  cov: C ft: F corp: K/S ..."
    last=$(grep -E '^#[0-9]+' "$log" | tail -1 || true)
    execs=$(echo "$last" | sed -nE 's/^#([0-9]+).*/\1/p')
    cov=$(echo "$last" | sed -nE 's/.*cov: ([0-9]+).*/\1/p')
    ft=$(echo "$last" | sed -nE 's/.* ft: ([0-9]+).*/\1/p')
    corp=$(echo "$last" | sed -nE 's/.*corp: ([0-9]+)\/.*/\1/p')
    rate=$(sed -nE 's/^stat::average_exec_per_sec:[[:space:]]*([0-9]+)/\1/p' "$log" | tail -1)
    crashes=$((after - before))
    summary+=("$(printf '%-14s rc=%-3s execs=%-10s exec/s=%-7s cov=%-6s ft=%-6s corpus=%-6s new-artifacts=%s' \
        "$target" "$rc" "${execs:-?}" "${rate:-?}" "${cov:-?}" "${ft:-?}" "${corp:-?}" "$crashes")")
    if [ "$rc" -ne 0 ] || [ "$crashes" -ne 0 ]; then
        status=1
        grep -E 'panicked|ERROR: |SUMMARY' "$log" | head -5 || true
    fi
done

echo
echo "== summary (${seconds}s per target)"
printf '%s\n' "${summary[@]}"
exit $status
