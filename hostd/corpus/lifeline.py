"""The processes of a local corpus run die with their driver: a SIGKILLed driver leaves no fork
server, worker or resource tracker behind (Linux: PR_SET_PDEATHSIG; elsewhere nothing is done).

The fork server preloads this module (hostd.corpus.run): when it is a child of the driver named
in HOSTD_CORPUS_DRIVER, it asks the kernel for SIGKILL when the driver dies. Each worker, a
child of the fork server, asks the same in its initializer (`die_with_parent`). The resource
tracker then sees its pipe closed by everyone and exits.
"""

from __future__ import annotations

import os
import signal
import sys

ENV = "HOSTD_CORPUS_DRIVER"
PR_SET_PDEATHSIG = 1


def die_with_parent(expected_parent: int | None = None) -> None:
    """SIGKILL this process when its parent dies (at once when it has died already)."""
    if not sys.platform.startswith("linux"):
        return
    import ctypes

    parent = expected_parent if expected_parent is not None else os.getppid()
    libc = ctypes.CDLL(None, use_errno=True)
    libc.prctl(PR_SET_PDEATHSIG, int(signal.SIGKILL), 0, 0, 0)
    if os.getppid() != parent:  # it died before the request
        os._exit(1)


def _when_preloaded() -> None:
    """In the fork server only: `python -c "from multiprocessing.forkserver import main; ..."`,
    started by the driver named in the environment."""
    driver = os.environ.get(ENV)
    if driver and driver == str(os.getppid()) and sys.argv[:1] == ["-c"] \
            and "multiprocessing.forkserver" in sys.modules:
        die_with_parent(int(driver))


_when_preloaded()
