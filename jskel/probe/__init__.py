"""Probes: what one measurement is, shared by the harness (``jskel.measure``: bench, sweep,
latency) and the peers' studies (``jskel.peers``), which do not import each other.

* ``timing``: compile apart, warm-up, the median of warm runs;
* ``cast``: the cast alone, timed as the peers' casts are (host rays, or rays resident on the
  device);
* ``metrics``: errors of a render against a reference (float64 NumPy);
* ``study``: what every peer study is given (``StudyOptions``) and how its depths are scored.
"""
