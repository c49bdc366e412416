"""Progress bars for long host work (fits, cell membership, builds, renders, sweeps): shown on a
terminal and in a notebook (``tqdm.auto``), never in CI, nor where standard error is neither a
terminal nor a notebook's; the executor's render bar (``executor.map_chunks``) and the sweep's
follow :func:`quiet` too."""

from __future__ import annotations

import contextlib
import os
import sys
import threading


def in_notebook() -> bool:
    """Whether this process is a Jupyter kernel: its standard error is not a terminal
    (ipykernel's stream says so), yet ``tqdm.auto`` shows its bars there as widgets."""
    ipython = sys.modules.get("IPython")
    shell = None if ipython is None else ipython.get_ipython()
    return getattr(shell, "kernel", None) is not None


def quiet() -> bool:
    """Whether to hide progress: ``CI`` is set, or standard error is not a terminal outside a
    notebook."""
    return bool(os.environ.get("CI")) or not (sys.stderr.isatty() or in_notebook())


def bar(total: int, desc: str, unit: str):
    """A ``tqdm.auto`` bar of ``total`` steps (elapsed time and rate are tqdm's own), disabled
    where :func:`quiet` says so; use it as a context manager and call ``update(n)``."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=quiet(), leave=False)


@contextlib.contextmanager
def notice_after(delay: float, message: str):
    """Say ``jskel: MESSAGE ...`` on standard error once the work inside has taken ``delay``
    seconds (a timer thread; where :func:`quiet` allows): a long build says what it is doing
    while it runs, a short one says nothing. (A delayed tqdm bar shows only at an update, so a
    one-step build would show its bar after it ended.)"""
    timer = None
    if not quiet():
        timer = threading.Timer(delay, lambda: print(f"jskel: {message} ...", file=sys.stderr, flush=True))
        timer.daemon = True
        timer.start()
    try:
        yield
    finally:
        if timer is not None:
            timer.cancel()
