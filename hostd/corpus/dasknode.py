"""The Dask side of `hostd corpus run --dask`: a local cluster that only its owner can reach.

Dask's plain `tcp://` has no authentication: any local account that finds a listener can
connect a Client and run a function in a worker, as the user who runs the corpus. So a
`--dask local` cluster uses Dask's temporary TLS (`Security.temporary()`: a key and a
self-signed certificate made in memory for this run, handed to the worker processes through
their spawn pipes, never written to a file other accounts can read). Every listener (scheduler,
nannies, workers) then requires a client certificate signed by that key: a connection without
it fails in the TLS handshake.

No HTTP server either: Dask starts one on the scheduler (8787, or any free port) and on every
worker, whatever `dashboard_address` says. Here they serve no route (an empty route list) on
loopback and are closed as soon as the cluster is up: the scheduler's at once, each worker's
(a restarted one's too) by a worker plugin when it starts.

A remote cluster (`--dask tls://HOST:8786` or `tcp://...`) is the user's: give its TLS
credentials through Dask's own configuration (docs/corpus.md, "Where it runs").
"""

from __future__ import annotations

import os

from distributed import Client, LocalCluster, WorkerPlugin

NO_ROUTES = {"distributed.scheduler.http.routes": [], "distributed.worker.http.routes": []}


class CloseHttp(WorkerPlugin):
    """On each worker as it starts: close its HTTP server's listening sockets."""

    name = "hostd-close-http"

    def setup(self, worker) -> None:
        srv = getattr(worker, "http_server", None)
        if srv is not None:
            srv.stop()


def _close_scheduler_http(dask_scheduler=None) -> None:
    srv = getattr(dask_scheduler, "http_server", None)
    if srv is not None:
        srv.stop()


def local_cluster(workers: int) -> tuple[LocalCluster, Client]:
    """A LocalCluster of `workers` processes x 1 thread on 127.0.0.1 over mutual TLS, no HTTP
    server left listening, and its Client."""
    import dask

    from hostd.extras import need

    need("cryptography", "corpus", "--dask local (the cluster's TLS)")
    # no dashboard here, so no use for the workers' statistical profiler (it samples every
    # thread every 10 ms: CPU taken from the jobs)
    os.environ.setdefault("DASK_DISTRIBUTED__WORKER__PROFILE__ENABLED", "False")
    with dask.config.set(NO_ROUTES):  # the nannies pass this configuration on to their workers
        cluster = LocalCluster(n_workers=workers, threads_per_worker=1, processes=True,
                               host="127.0.0.1", security=True, dashboard_address="127.0.0.1:0",
                               worker_dashboard_address="127.0.0.1:0")
    try:
        client = Client(cluster)
        client.run_on_scheduler(_close_scheduler_http)
        client.register_plugin(CloseHttp())
    except BaseException:
        cluster.close()
        raise
    return cluster, client
