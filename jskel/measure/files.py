"""What a measurement reads and writes: experiments, bench and sweep files, JSON lines.

The CLI, the bench and the sweep load experiments through :func:`load_experiment`; nothing here
or elsewhere in the package imports the CLI. Bad input is a ``ConfigError`` naming every bad key
(the CLI prints one line each and exits 2, before anything compiles).
"""

from __future__ import annotations

import json
from pathlib import Path

import jax
from pydantic import BaseModel, ValidationError

from ..config import ConfigError, _format, apply_overrides, read_yaml, validate

#: ``--x64``: the precision switch, set at an entry point only
X64 = ["render.dtype=float64"]


def _enable_x64_if_asked(raw: dict):
    """x64 is switched on here, at the entry point, when the experiment asks for float64 (before
    anything compiles); library code never switches it."""
    render = raw.get("render") if isinstance(raw, dict) else None
    if isinstance(render, dict) and render.get("dtype") == "float64":
        jax.config.update("jax_enable_x64", True)


def load_experiment(path, overrides: list[str]):
    """Read an experiment file (None: the embedded default), apply ``key=value`` overrides,
    validate it and switch x64 on if it asks for float64. Returns (experiment, object config)."""
    raw = apply_overrides(read_yaml(path), overrides)
    exp, obj = validate(raw)
    _enable_x64_if_asked(raw)
    return exp, obj


def read_model(model: type[BaseModel], path, overrides: list[str]):
    """A bench, sweep or fit file, overridden and validated (every bad key at once)."""
    raw = apply_overrides(read_yaml(path), overrides)
    try:
        return model.model_validate(raw)
    except ValidationError as e:
        raise ConfigError(_format(e)) from None


def beside(name: str, file, field: str) -> Path:
    """``name`` as given, or relative to the folder of ``file`` (a bench's scenes, a sweep's
    base); a ``ConfigError`` naming ``field`` when neither exists."""
    p = Path(name)
    if p.exists():
        return p
    p = Path(file).parent / name
    if not p.exists():
        raise ConfigError([f"{field}: file not found (got {name!r})"])
    return p


class JsonLines:
    """Rows printed as JSON lines as they are measured and, with ``out``, appended to that file
    (emptied first), so an interrupted benchmark keeps the rows it measured."""

    def __init__(self, out=None):
        self.out = None if out is None else Path(out)
        if self.out is not None:
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self.out.write_text("")

    def __call__(self, row: dict, keep: bool = True):
        """Print ``row``; also append it to ``out`` unless ``keep`` is False (a log line)."""
        line = json.dumps(row)
        print(line, flush=True)
        if keep and self.out is not None:
            with self.out.open("a") as f:
                f.write(line + "\n")
