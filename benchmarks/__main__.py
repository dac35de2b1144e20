"""python -m benchmarks [WHAT] [--json]  — the same as `hostd bench` (./run bench)."""

import sys

from hostd.cli import main

raise SystemExit(main(["bench", *sys.argv[1:]]))
