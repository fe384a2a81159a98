"""Set-up of the worker processes of the sweeps' LocalCluster (a Dask preload: ``dask_setup`` runs in each
worker process as it starts, on its main thread).

The workers are this program's own processes, started for a sweep:

* they ignore SIGINT. A terminal's Ctrl-C goes to the whole process group; the driver process handles it
  (one line, the journal kept) and closes the cluster, so the workers have nothing to say (each would print a
  KeyboardInterrupt traceback);
* Warp is quiet in them (:func:`terrainwarp.configure`), and each launch runs on one thread (a sweep's
  parallelism is its processes, one a core).
"""

from __future__ import annotations

import contextlib
import signal

from ..runtime import configure

__all__ = ["dask_setup", "PRELOAD"]

PRELOAD = __name__  # the module name LocalCluster(preload=[...]) imports in every worker


def dask_setup(worker: object = None) -> None:
    """Ignore SIGINT and configure terrainwarp for a sweep worker (called by Dask with the worker)."""
    with contextlib.suppress(ValueError):  # not the main thread: the worker then runs as Dask set it up
        signal.signal(signal.SIGINT, signal.SIG_IGN)
    configure(quiet=True, threads=1)
