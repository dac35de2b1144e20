#!/bin/sh
# Build hostd/device/_fastlink.c with AddressSanitizer and UndefinedBehaviorSanitizer (clang, with
# libFuzzer's coverage, so the C decoder's branches guide the fuzzer too) into FUZZ_OUT (default a
# temporary directory) and run the atheris harness of the Python paths against that build:
#     tests/fuzz/sanitize_device_link.sh -max_total_time=20 [atheris/libFuzzer options] [corpus]
# Exit status: non-zero on a finding (a crash, a sanitizer report, a divergence) or a build failure.
# ASan's runtime with the fuzzer is atheris's own (asan_with_fuzzer.so, preloaded);
# PYTHONMALLOC=malloc gives Python's buffers (the messages decoded) ASan's red zones.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
out=${FUZZ_OUT:-$(mktemp -d)}
mkdir -p "$out"  # a FUZZ_OUT that does not exist yet is made
py=${PYTHON:-python3}
inc=$("$py" -c 'import sysconfig; print(sysconfig.get_paths()["include"])')
so="$out/_fastlink$("$py" -c 'import sysconfig; print(sysconfig.get_config_var("EXT_SUFFIX"))')"
clang -shared -fPIC -g -O1 -fno-omit-frame-pointer -fsanitize=address,undefined,fuzzer-no-link \
    -fno-sanitize-recover=undefined -I"$inc" -I"$here/../../firmware/include" "$here/../../hostd/device/_fastlink.c" \
    "$here/../../firmware/src/framing.c" -o "$so"
asan="$("$py" -c 'import atheris; print(atheris.path())')/asan_with_fuzzer.so"
LD_PRELOAD="$asan" PYTHONMALLOC=malloc ASAN_OPTIONS=detect_leaks=0 UBSAN_OPTIONS=halt_on_error=1 \
    HOSTD_FASTLINK_SO="$so" "$py" "$here/fuzz_device_link.py" "$@"
