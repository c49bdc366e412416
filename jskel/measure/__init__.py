"""Measurement: one harness for ``jskel bench`` and ``jskel sweep``.

* ``files``: experiments, bench and sweep files loaded for every command (the CLI included),
  JSON-lines output;
* ``grid``: one grid expansion (value lists, ranges, explicit settings) for both;
* ``timing``: compile apart, warm-up, the median of warm runs;
* ``cast``: the cast alone, timed as the peers' casts are (host rays, or rays resident on the
  device);
* ``metrics``: errors of a render against a reference (float64 NumPy);
* ``plots``, ``results``: bars, error against time with the Pareto front, cost against size;
  a sweep's ``results.csv`` and ``report.md``;
* ``bench``, ``sweep``: the two commands, each a short sequence of the above (import them as
  ``jskel.measure.bench`` and ``jskel.measure.sweep``); the peers' studies are ``jskel.peers``;
* ``latency``: time to first image, fresh processes with an empty and a warm compilation cache
  and re-renders after a change (``jskel bench`` of a file with a ``latency:`` section).
"""

from .cast import cast_once as cast_once
from .cast import cast_resident as cast_resident
from .cast import resident_rays as resident_rays
from .cast import timed_cast as timed_cast
from .files import load_experiment as load_experiment
from .files import read_model as read_model
from .grid import Range as Range
from .grid import expand as expand
from .metrics import compare as compare
from .metrics import depth_in_pixels as depth_in_pixels
from .metrics import pareto_front as pareto_front
from .metrics import ssim as ssim
from .metrics import uv_rmse as uv_rmse
from .timing import render_runs as render_runs
from .timing import spread as spread
from .timing import warm_runs as warm_runs

__all__ = ["Range", "cast_once", "cast_resident", "compare", "depth_in_pixels", "expand", "load_experiment", "pareto_front",
           "read_model", "render_runs", "resident_rays", "spread", "ssim", "timed_cast", "uv_rmse", "warm_runs"]
