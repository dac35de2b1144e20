#!/bin/sh
# Build the libFuzzer harnesses of the compiled device-link parsers (clang, ASan + UBSan) and run
# each for SECONDS (default 20) or RUNS executions: tests/fuzz/run_fuzzers.sh [SECONDS] [RUNS]
# Exit status: non-zero on a finding (a crash, a sanitizer report, a divergence) or a build failure.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
secs=${1:-20}
runs=${2:--1}
out=${FUZZ_OUT:-$(mktemp -d)}
mkdir -p "$out"  # a FUZZ_OUT that does not exist yet is made
py=${PYTHON:-python3}
inc=$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
libdir=$("$py" -c 'import sysconfig; print(sysconfig.get_config_var("LIBDIR"))')
ver=$("$py" -c 'import sysconfig; print(sysconfig.get_config_var("LDVERSION"))')
np_inc=$("$py" -c 'import numpy; print(numpy.get_include())')
"$py" "$here/../../hostd/cyclestate.py"  # hostd/device/cycle_state.h, as setup.py generates it
for h in fuzz_fastpump_deframe fuzz_fastpump_status fuzz_fastlink_decode; do
    clang -g -O1 -fsanitize=fuzzer,address,undefined -fno-sanitize-recover=undefined \
        -I"$inc" -I"$np_inc" -I"$here/../../hostd/device" -I"$here/../../firmware/include" "$here/$h.c" \
        "$here/../../firmware/src/framing.c" -o "$out/$h" \
        -L"$libdir" -Wl,-rpath,"$libdir" -lpython"$ver" -lm
    mkdir -p "$out/$h.corpus"
    # Python's own allocations at start-up are not leaks of the harness
    ASAN_OPTIONS=detect_leaks=0 UBSAN_OPTIONS=halt_on_error=1 \
        "$out/$h" -max_total_time="$secs" -runs="$runs" -print_final_stats=1 "$out/$h.corpus" \
        2>"$out/$h.log" || { tail -40 "$out/$h.log"; exit 1; }
    echo "$h: $(grep -o 'stat::number_of_executed_units: *[0-9]*' "$out/$h.log" | grep -o '[0-9]*$') executions"
done
