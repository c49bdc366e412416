"""Representations by the name an experiment's ``object.type`` gives.

A representation is a module attribute implementing :class:`jskel.interface.Representation`.
Adding one is a folder and one line here; entries are imported lazily so a representation's
dependencies load only when an experiment uses it.
"""

from __future__ import annotations

import importlib

_ENTRIES = {
    "frusta": "jskel.frusta:REPRESENTATION",
    "implicit": "jskel.implicit:REPRESENTATION",
    "cells": "jskel.cells:REPRESENTATION",
    "mesh": "jskel.mesh:REPRESENTATION",
}


def names() -> list[str]:
    """Registered representation names, sorted."""
    return sorted(_ENTRIES)


def get(name: str):
    """The representation registered as ``name``; ValueError naming ``object.type`` otherwise."""
    try:
        target = _ENTRIES[name]
    except KeyError:
        raise ValueError(f"object.type: unknown representation {name!r} (known: {', '.join(names())})") from None
    mod, attr = target.split(":")
    return getattr(importlib.import_module(mod), attr)
