"""What keeps the supervising processes lean: the daemon and its pump need no BLAS threads.

numpy's OpenBLAS starts one thread per core when it loads (16 on a 16-core PC), and keeps them
for the life of the process; nothing the daemon or the pump computes is a matrix product worth
a second core. The thread count is read from the environment when the library loads, so it is
set before numpy is imported: by `hostd run` first thing (hostd.service.cli.cmd_run), and for
the pump by the daemon around its start (the spawned pump imports numpy anew and inherits the
environment), also when the daemon runs inside another process (tests, an embedding program).
OPENBLAS_CORETYPE is left alone (the same bytes on every CPU do not depend on it here).
"""

from __future__ import annotations

import contextlib
import os

ONE_THREAD = {"OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}


def one_blas_thread_env() -> None:
    """This process (before numpy loads) and every child it starts afterwards: one BLAS thread."""
    os.environ.update(ONE_THREAD)


@contextlib.contextmanager
def children_with_one_blas_thread():
    """Children started inside the block get one BLAS thread; the environment is restored after."""
    saved = {k: os.environ.get(k) for k in ONE_THREAD}
    os.environ.update(ONE_THREAD)
    try:
        yield
    finally:
        for k, v in saved.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v
