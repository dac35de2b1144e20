"""Logging of `hostd run`: journald priorities, timestamps in the foreground, repeats rate-limited.

- Under systemd (stderr is the journal: $JOURNAL_STREAM names it) every line starts with its
  syslog priority, ``<3>`` error, ``<4>`` warning, ``<6>`` info, ``<7>`` debug, which journald
  turns into the entry's priority (so `journalctl -p warning` shows failures); the journal adds
  the time itself.
- Elsewhere (a terminal, a file) lines carry a timestamp and no prefix.
- A message identical to an earlier one (the same text: "no display found" every second while
  none is plugged in) is let through again only after a back-off that doubles from 1 s to
  10 min, with the number of repeats held back; a different message resets nothing else.
- Control characters in a message are escaped (a name with a newline cannot forge a line).
"""

from __future__ import annotations

import logging
import os
import re
import sys
import threading
import time

PRIORITY = {logging.CRITICAL: 2, logging.ERROR: 3, logging.WARNING: 4, logging.INFO: 6, logging.DEBUG: 7}
BACKOFF_START_S = 1.0
BACKOFF_MAX_S = 600.0


def under_journald(stream=None) -> bool:
    """True when the stream is the journal's ($JOURNAL_STREAM = device:inode of it)."""
    stream = stream or sys.stderr
    js = os.environ.get("JOURNAL_STREAM", "")
    if not js:
        return False
    try:
        dev, ino = (int(x) for x in js.split(":"))
        st = os.fstat(stream.fileno())
    except (ValueError, OSError, AttributeError):
        return False
    return (st.st_dev, st.st_ino) == (dev, ino)


# Control characters (newline, carriage return, escape sequences) and Unicode line breaks in a
# message are shown escaped (\n, \x1b): a client's text cannot forge or hide a log line.
CONTROL_CHARS = re.compile("[\x00-\x1f\x7f-\x9f\u2028\u2029]")


def escape_controls(text: str) -> str:
    return CONTROL_CHARS.sub(lambda m: repr(m.group())[1:-1], text)


class EscapingFormatter(logging.Formatter):
    """Escapes the message's control characters (a traceback, added after, keeps its lines)."""

    def formatMessage(self, record: logging.LogRecord) -> str:
        record.message = escape_controls(record.message)
        return super().formatMessage(record)


class JournalFormatter(EscapingFormatter):
    def format(self, record: logging.LogRecord) -> str:
        prio = PRIORITY.get(record.levelno, 6)
        return f"<{prio}>" + super().format(record)


class RepeatFilter(logging.Filter):
    """Rate-limits repeats of the same message text with a doubling back-off."""

    def __init__(self, clock=time.monotonic) -> None:
        super().__init__()
        self.clock = clock
        self.state: dict[str, list[float]] = {}  # text -> [next allowed time, back-off, held back]
        self.lock = threading.Lock()

    def filter(self, record: logging.LogRecord) -> bool:
        text = record.getMessage()
        now = self.clock()
        with self.lock:
            st = self.state.get(text)
            if st is None:
                if len(self.state) > 1000:  # bounded memory
                    self.state.clear()
                self.state[text] = [now + BACKOFF_START_S, BACKOFF_START_S, 0]
                return True
            if now < st[0]:
                st[2] += 1
                return False
            held = int(st[2])
            st[1] = min(st[1] * 2, BACKOFF_MAX_S)
            st[0] = now + st[1]
            st[2] = 0
        if held:
            record.msg = f"{text} (repeated {held} more times; next report in {st[1]:g} s at most)"
            record.args = ()
        return True


def setup(level: str = "info", stream=None) -> logging.Handler:
    stream = stream or sys.stderr
    handler = logging.StreamHandler(stream)
    if under_journald(stream):
        handler.setFormatter(JournalFormatter("hostd %(levelname)s %(message)s"))
    else:
        handler.setFormatter(EscapingFormatter("%(asctime)s hostd %(levelname)s %(message)s"))
    handler.addFilter(RepeatFilter())
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(getattr(logging, level.upper()))
    return handler
