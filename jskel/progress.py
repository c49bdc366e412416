"""Progress bars for long host work (fits, cell membership, builds, renders, sweeps): shown on a
terminal and in a notebook (``tqdm.auto``), never in CI, nor where standard error is neither a
terminal nor a notebook's; the executor's render bar (``executor.map_chunks``) and the sweep's
follow :func:`quiet` too."""

from __future__ import annotations

import os
import sys


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


def bar(total: int, desc: str, unit: str, delay: float = 0.0):
    """A ``tqdm.auto`` bar of ``total`` steps (elapsed time and rate are tqdm's own), disabled
    where :func:`quiet` says so, shown once ``delay`` seconds have passed (work that ends sooner
    shows none); use it as a context manager and call ``update(n)``."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=quiet(), leave=False, delay=delay)
