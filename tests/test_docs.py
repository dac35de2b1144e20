"""The docs site: its generated references are current, and every command block of the tutorials
and how-to guides runs as written.

A ```sh block of docs/tutorials/ or docs/how-to/ runs in CI, one page as one bash session in an
empty folder with this environment's `hostd` first on PATH (a page's blocks build on each other).
The only blocks skipped are those marked on the line before with `<!-- not run: REASON -->`, and
REASON must say it needs root, systemd, hardware or a person. A block that fails, or that uses a
deprecated spelling of an option, fails here.
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
DOCS = ROOT / "docs"
RUNNABLE = sorted([*DOCS.glob("tutorials/*.md"), *DOCS.glob("how-to/*.md")])
SKIP_MARK = re.compile(r"<!--\s*not run:\s*(.+?)\s*-->")
SKIP_REASONS = ("root", "systemd", "hardware", "a person", "a display")
FENCE = re.compile(r"^```(\w*)\s*$")


def blocks(page: Path) -> list[tuple[int, str, str | None]]:
    """(line, code, skip reason or None) of every ```sh block of a page."""
    out, lines = [], page.read_text(encoding="utf-8").splitlines()
    i = 0
    while i < len(lines):
        m = FENCE.match(lines[i])
        if m and m.group(1) in ("sh", "bash", "console"):
            start, body = i + 1, []
            i += 1
            while i < len(lines) and not lines[i].startswith("```"):
                body.append(lines[i])
                i += 1
            before = next((ln for ln in reversed(lines[:start - 1]) if ln.strip()), "")
            skip = SKIP_MARK.search(before)
            out.append((start, "\n".join(body), skip.group(1) if skip else None))
        i += 1
    return out


def test_there_are_four_tutorials_and_the_how_to_guides():
    names = {p.stem for p in DOCS.glob("tutorials/*.md")}
    assert {"first-texture", "first-corpus", "calibrate-iobj", "display-pc"} <= names
    assert len(list(DOCS.glob("how-to/*.md"))) >= 7


@pytest.mark.parametrize("page", RUNNABLE, ids=[p.relative_to(DOCS).as_posix() for p in RUNNABLE])
def test_every_command_block_runs_as_written(page, tmp_path):
    found = blocks(page)
    for line, _code, reason in found:
        if reason is not None:
            assert any(r in reason for r in SKIP_REASONS), \
                f"{page.name}:{line}: a block is skipped only when it needs root, systemd, hardware or " \
                f"a person, and says so (<!-- not run: needs root: ... -->), not {reason!r}"
    script = ["set -euo pipefail"]
    for n, (line, code, reason) in enumerate(found):
        if reason is None:
            script += [f"echo '::block {n} (line {line})::' >&2", code]
    if len(script) == 1:
        pytest.skip(f"{page.name}: no block to run")
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}:{os.environ.get('PATH', '')}",
           "HOSTD_CONFIG": "", "PYTHONWARNINGS": "default"}
    r = subprocess.run(["bash", "-c", "\n".join(script)], cwd=tmp_path, env=env, capture_output=True,
                       text=True, timeout=600)
    where = re.findall(r"::block \d+ \(line (\d+)\)::", r.stderr)
    assert r.returncode == 0, (f"{page.relative_to(ROOT)}: the block at line {where[-1] if where else '?'} "
                               f"failed (exit {r.returncode}):\n{r.stderr[-3000:]}")
    assert "is deprecated" not in r.stderr + r.stdout, \
        f"{page.relative_to(ROOT)} uses a deprecated option spelling:\n" + "\n".join(
            ln for ln in (r.stderr + r.stdout).splitlines() if "is deprecated" in ln)


def test_the_cli_reference_is_generated_from_the_parser():
    from hostd.docgen import cli_markdown
    from hostd.parser import build_parser

    assert (DOCS / "reference" / "cli.md").read_text(encoding="utf-8") == cli_markdown(build_parser()), \
        "docs/reference/cli.md is stale: hostd manpage --markdown > docs/reference/cli.md"


def test_no_docs_page_carries_an_issue_number_or_a_run_timestamp():
    bad = []
    for page in DOCS.rglob("*.md"):
        text = page.read_text(encoding="utf-8")
        for pat in (r"\b(?:issue|Issue) #?\d+\b", r"\b\d{2}:\d{2}(?::\d{2})?\s*UTC\b"):
            bad += [f"{page.relative_to(ROOT)}: {m.group(0)}" for m in re.finditer(pat, text)]
    assert not bad, "docs/ holds issue numbers or run timestamps (they belong in DEVELOPMENT.md): " + \
        "; ".join(bad[:20])
