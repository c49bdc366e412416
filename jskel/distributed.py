"""Several hosts (issue 6): each process renders its share of the image's rays.

Start the same command on every host with three environment variables::

    JSKEL_COORDINATOR=host0:12355 JSKEL_NUM_PROCESSES=2 JSKEL_PROCESS_ID=0 python -m jskel render ...
    JSKEL_COORDINATOR=host0:12355 JSKEL_NUM_PROCESSES=2 JSKEL_PROCESS_ID=1 python -m jskel render ...

:func:`init_from_env` calls ``jax.distributed.initialize`` (CPU collectives through gloo).
``render`` then gives process k the k-th contiguous share of the screen-tile-ordered rays
(a whole number of chunks), traces it on that host's local devices, and gathers every share
with ``multihost_utils.process_allgather``; process 0 writes the outputs. Per-ray results do not
depend on which chunk or process traced them, so the image equals a one-process render bit for
bit (tested with two processes on loopback).
"""

from __future__ import annotations

import os

_ENV = ("JSKEL_COORDINATOR", "JSKEL_NUM_PROCESSES", "JSKEL_PROCESS_ID")


def init_from_env() -> bool:
    """Initialize jax.distributed when the JSKEL_* variables are set; returns whether it did."""
    if not os.environ.get("JSKEL_COORDINATOR"):
        return False
    missing = [k for k in _ENV if not os.environ.get(k)]
    if missing:
        raise ValueError(f"{missing[0]}: must be set with JSKEL_COORDINATOR (got nothing)")
    import jax

    try:
        n, pid = int(os.environ["JSKEL_NUM_PROCESSES"]), int(os.environ["JSKEL_PROCESS_ID"])
    except ValueError:
        raise ValueError(f"JSKEL_NUM_PROCESSES / JSKEL_PROCESS_ID: must be integers (got {os.environ['JSKEL_NUM_PROCESSES']!r}, {os.environ['JSKEL_PROCESS_ID']!r})") from None
    if not (n >= 1 and 0 <= pid < n):
        raise ValueError(f"JSKEL_PROCESS_ID: must lie in [0, {n}) (got {pid})")
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=os.environ["JSKEL_COORDINATOR"], num_processes=n, process_id=pid)
    return True


def share(n: int, chunk: int, processes: int, index: int) -> tuple[int, int]:
    """[start, stop) of process ``index``'s rays: equal shares of whole chunks."""
    per = -(-(-(-n // chunk)) // processes) * chunk
    start = min(index * per, n)
    return start, min(start + per, n)


def gather(tree, n_local: int, per: int):
    """All processes' (per, ...) leading-axis arrays, concatenated in process order."""
    import numpy as np
    from jax.experimental import multihost_utils

    import jax

    def pad(a):
        a = np.asarray(a)
        out = np.zeros((per,) + a.shape[1:], a.dtype)
        out[:n_local] = a
        return out

    padded = jax.tree_util.tree_map(pad, tree)
    counts = multihost_utils.process_allgather(np.array([n_local]))
    full = multihost_utils.process_allgather(padded)
    return jax.tree_util.tree_map(lambda a: np.concatenate([a[k][: int(counts[k][0])] for k in range(a.shape[0])]), full)
