#!/usr/bin/env bash
# Build hostd/codec/_rangecoder.c with AddressSanitizer and UndefinedBehaviorSanitizer (gcc) into
# a temporary directory and run the differential harness against that build:
#     tests/fuzz/sanitize_rangecoder.sh --random 10000      (about 40 s)
# Any out-of-bounds access or undefined behaviour in the C coder aborts with a report
# (PYTHONMALLOC=malloc: the payloads get ASan red zones; Python itself is not instrumented).
set -euo pipefail
cd "$(dirname "$0")/../.."
PY=${PYTHON:-.venv/bin/python}
out=$(mktemp -d)
trap 'rm -rf "$out"' EXIT
inc=$("$PY" -c "import sysconfig; print(sysconfig.get_paths()['include'])")
so="$out/_rangecoder$("$PY" -c "import sysconfig; print(sysconfig.get_config_var('EXT_SUFFIX'))")"
gcc -shared -fPIC -O1 -g -fno-omit-frame-pointer -fsanitize=address,undefined \
    -fno-sanitize-recover=all -I"$inc" hostd/codec/_rangecoder.c -o "$so"
LD_PRELOAD="$(gcc -print-file-name=libasan.so):$(gcc -print-file-name=libubsan.so)" \
PYTHONMALLOC=malloc ASAN_OPTIONS=detect_leaks=0 HOSTD_RANGECODER_SO="$so" PYTHONPATH=. "$PY" tests/fuzz/fuzz_rangecoder.py "$@"
