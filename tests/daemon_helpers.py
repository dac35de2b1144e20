"""Helpers for tests that run the real daemon: waiting on its control socket."""

from __future__ import annotations

import time

import pytest

from hostd.service.client import ClientError


def wait_for(pred, timeout_s: float, what: str):
    """pred()'s first truthy value within timeout_s (a daemon not answering yet is retried)."""
    t_end = time.monotonic() + timeout_s
    while time.monotonic() < t_end:
        try:
            v = pred()
            if v:
                return v
        except ClientError:
            pass
        time.sleep(0.05)
    pytest.fail(f"timed out waiting for {what}")
