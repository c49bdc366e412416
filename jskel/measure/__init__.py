"""Measurement: one harness for ``jskel bench`` and ``jskel sweep``.

* ``files``: experiments, bench and sweep files loaded for every command (the CLI included),
  JSON-lines output;
* ``grid``: one grid expansion (value lists, ranges, explicit settings) for both;
* ``timing``, ``cast``, ``metrics`` (re-exported here) live in ``jskel.probe``, which the peers'
  studies share;
* ``plots``, ``results``: bars, error against time with the Pareto front, cost against size;
  a sweep's ``results.csv`` and ``report.md``;
* ``bench``, ``sweep``: the two commands, each a short sequence of the above (import them as
  ``jskel.measure.bench`` and ``jskel.measure.sweep``); the peers' studies (``jskel.peers``) are
  handed to them by the CLI (``studies``, ``peer``, ``mitsuba``): neither folder imports the other;
* ``latency``: time to first image, fresh processes with an empty and a warm compilation cache
  and re-renders after a change (``jskel bench`` of a file with a ``latency:`` section).
"""

from ..probe.cast import cast_once as cast_once
from ..probe.cast import cast_resident as cast_resident
from ..probe.cast import resident_rays as resident_rays
from ..probe.cast import timed_cast as timed_cast
from .files import read_model as read_model
from .grid import Range as Range
from .grid import expand as expand
from ..probe.metrics import compare as compare
from ..probe.metrics import depth_in_pixels as depth_in_pixels
from ..probe.metrics import pareto_front as pareto_front
from ..probe.metrics import ssim as ssim
from ..probe.metrics import uv_rmse as uv_rmse
from ..probe.timing import render_runs as render_runs
from ..probe.timing import spread as spread
from ..probe.timing import warm_runs as warm_runs

__all__ = ["Range", "cast_once", "cast_resident", "compare", "depth_in_pixels", "expand", "pareto_front",
           "read_model", "render_runs", "resident_rays", "spread", "ssim", "timed_cast", "uv_rmse", "warm_runs"]
