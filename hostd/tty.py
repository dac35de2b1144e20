"""Progress bars and status lines only where a person watches: on a terminal. A log file, a pipe
or systemd's journal gets neither (no bar redrawn with '\\r' in a log)."""

from __future__ import annotations

import sys


def on_terminal(stream=None) -> bool:
    stream = sys.stderr if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed, or not a file
        return False


def progress_bar(enabled: bool = True, **kw):
    """tqdm on stderr, shown only when `enabled` and stderr is a terminal."""
    from tqdm import tqdm

    kw.setdefault("file", sys.stderr)
    return tqdm(disable=not (enabled and on_terminal(kw["file"])), **kw)
