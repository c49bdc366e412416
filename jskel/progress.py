"""Progress bars for long host work (fits, cell membership): shown on a terminal and in a
notebook (``tqdm.auto``), never in CI or when standard error is not a terminal, as the
executor's render bar (``executor.map_chunks``)."""

from __future__ import annotations

import os
import sys


def quiet() -> bool:
    """Whether to hide progress: standard error is not a terminal, or ``CI`` is set."""
    return not sys.stderr.isatty() or bool(os.environ.get("CI"))


def bar(total: int, desc: str, unit: str):
    """A ``tqdm.auto`` bar of ``total`` steps (elapsed time and rate are tqdm's own), disabled
    where :func:`quiet` says so; use it as a context manager and call ``update(n)``."""
    from tqdm.auto import tqdm

    return tqdm(total=total, desc=desc, unit=unit, disable=quiet(), leave=False)
