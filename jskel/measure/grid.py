"""Settings to measure: one grid expansion for the bench's ``sweep`` and the sweep's ``vary``.

A grid is a mapping of config keys to value lists (or :class:`Range`), expanded to their
cartesian product with the first key slowest, or an explicit list of settings (each a mapping of
keys to values) taken as written. A setting becomes ``key=value`` overrides of the experiment.
"""

from __future__ import annotations

import itertools
import json
import math
from typing import Annotated, Any

from pydantic import Field, model_validator

from ..config import StrictModel


class Range(StrictModel):
    """``num`` values from ``start`` to ``stop`` inclusive, evenly spaced, or geometrically with
    ``log: true``; ``integer: true`` rounds them (duplicates dropped)."""

    start: float
    """First value."""
    stop: float
    """Last value (inclusive)."""
    num: Annotated[int, Field(ge=1, le=10000)]
    """Number of values."""
    log: bool = False
    """Space geometrically (start and stop > 0) instead of evenly."""
    integer: bool = False
    """Round to integers (duplicates dropped)."""

    @model_validator(mode="after")
    def _positive_for_log(self):
        if self.log and (self.start <= 0 or self.stop <= 0):
            raise ValueError(f"a log range needs start and stop > 0 (got {self.start}, {self.stop})")
        return self

    def values(self) -> list:
        if self.num == 1:
            vals = [self.start]
        elif self.log:
            r = math.log(self.stop / self.start) / (self.num - 1)
            vals = [self.start * math.exp(r * i) for i in range(self.num)]
        else:
            vals = [self.start + (self.stop - self.start) * i / (self.num - 1) for i in range(self.num)]
        if self.integer:
            vals = list(dict.fromkeys(int(round(v)) for v in vals))
        return vals


def expand(grid: dict[str, list[Any] | Range] | list[dict[str, Any]]) -> list[dict]:
    """The settings of ``grid``, in order: an explicit list as written, or the cartesian product
    of a mapping's value lists (ranges expanded; the first key varies slowest)."""
    if isinstance(grid, list):
        return [dict(s) for s in grid]
    keys = list(grid)
    lists = [v.values() if isinstance(v, Range) else list(v) for v in grid.values()]
    return [dict(zip(keys, vals)) for vals in itertools.product(*lists)]


def keys_of(settings: list[dict]) -> list[str]:
    """Every key the settings vary, in order of first appearance."""
    return list(dict.fromkeys(k for s in settings for k in s))


def overrides_of(setting: dict) -> list[str]:
    """A setting as experiment overrides (``key=<JSON value>``)."""
    return [f"{k}={json.dumps(v)}" for k, v in setting.items()]


def setting_key(setting: dict) -> str:
    """The identity of a setting in a results file (JSON of its values, keys sorted)."""
    return json.dumps(setting, sort_keys=True)
