#!/bin/sh
# Run one atheris harness of tests/fuzz on a fresh machine:
#     tests/fuzz/run_atheris.sh HARNESS [SECONDS] [libFuzzer options...]
# HARNESS: fuzz_profiles (the profile readers), fuzz_stream (the .vtx decoders) or
# fuzz_rangecoder. FUZZ_OUT (default: a new temporary directory) is created if missing; the
# harness's seeds (tests/fuzz/corpus/profiles; the golden streams tests/vectors/*.vtx) are copied
# into $FUZZ_OUT/HARNESS.corpus, which the run grows (the repository is never written), and a
# finding is written to $FUZZ_OUT. Peak RSS is limited to FUZZ_RSS_MB (default 600).
# Exit status: non-zero on a finding.
set -eu
here=$(cd "$(dirname "$0")" && pwd)
root=$(cd "$here/../.." && pwd)
h=${1:?usage: tests/fuzz/run_atheris.sh HARNESS [SECONDS] [libFuzzer options]}
secs=${2:-60}
[ $# -ge 2 ] && shift 2 || shift $#
py=${PYTHON:-$root/.venv/bin/python}
[ -x "$py" ] || py=python3
case "$py" in /*) ;; */*) py="$(pwd)/$py" ;; esac  # the run goes on in $FUZZ_OUT
out=${FUZZ_OUT:-$(mktemp -d)}
mkdir -p "$out/$h.corpus"
out=$(cd "$out" && pwd)
case "$h" in
  fuzz_profiles) cp "$here/corpus/profiles/"* "$out/$h.corpus/" ;;
  fuzz_stream) cp "$root/tests/vectors/"*.vtx "$out/$h.corpus/" 2>/dev/null || true ;;
esac
cd "$out"
echo "$h: corpus $out/$h.corpus, findings in $out" >&2
PYTHONPATH="$root" OPENBLAS_NUM_THREADS=1 "$py" "$here/$h.py" -max_total_time="$secs" \
    -rss_limit_mb="${FUZZ_RSS_MB:-600}" -print_final_stats=1 "$@" "$out/$h.corpus"
