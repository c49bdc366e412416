"""What a measurement reads and writes: experiments, bench and sweep files, JSON lines.

The CLI, the bench and the sweep load experiments through ``jskel.config.load``, the one loader;
nothing here or elsewhere in the package imports the CLI. Bad input is a ``ConfigError`` naming every bad key
(the CLI prints one line each and exits 2, before anything compiles).
"""

from __future__ import annotations

import json
import os
import platform
import shlex
import subprocess
import sys
from datetime import datetime, timezone
from pathlib import Path

import jax
from pydantic import BaseModel, ValidationError

from ..config import ConfigError, _format, apply_overrides, read_yaml

#: ``--x64``: the precision switch, set at an entry point only
X64 = ["render.dtype=float64"]


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


def _cpu(info: str | None = None) -> str:
    """The host CPU as a measurement names it: cores, model name, family and model numbers (a
    name such as "AMD EPYC" or "Xeon CPU @ 2.20GHz" covers several generations) and widest
    vector unit ("2-core AMD EPYC (family 26, model 2), AVX-512"), from /proc/cpuinfo (or
    ``info``, its text) where there is one. Two CPUs sold under one name ("AMD EPYC") gave the frusta's and the fit's programs
    different last bits and different timings, so a figure names which one it came from."""
    model, flags, numbers = platform.processor() or platform.machine(), set(), ""
    try:
        info = Path("/proc/cpuinfo").read_text(errors="replace") if info is None else info
    except OSError:
        info = ""
    lines = info.splitlines()

    def field(name):
        return next((ln.split(":", 1)[1].strip() for ln in lines if ln.split(":", 1)[0].strip() == name), None)

    model = field("model name") or model
    flags = set((field("flags") or "").split())
    family, number = field("cpu family"), field("model")
    if family and number:
        numbers = f" (family {family}, model {number})"
    vector = "AVX-512" if "avx512f" in flags else "AVX2" if "avx2" in flags else ""
    return ", ".join(x for x in (f"{os.cpu_count()}-core {model}{numbers}", vector) if x)


def _commit() -> str | None:
    """The working tree's commit (short hash, ``+changes`` when tracked files differ from it),
    None outside a git checkout."""
    try:
        head = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, timeout=10)
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    if head.returncode != 0:
        return None
    return head.stdout.strip() + ("+changes" if dirty.returncode == 0 and dirty.stdout.strip() else "")


def command_line() -> str:
    """This process's command as it was typed: ``python -m jskel ...`` for the CLI."""
    main = Path(sys.argv[0])
    if main.name == "jskel" or main.parts[-2:] == ("jskel", "__main__.py"):
        return shlex.join(["python", "-m", "jskel", *sys.argv[1:]])
    return shlex.join([sys.executable, *sys.argv])


def provenance(command: str | None = None) -> dict:
    """What identifies a measurement: when it started (UTC), the commit, the machine, the
    command, the versions and, where set, ``XLA_FLAGS`` (options that change every compiled
    program: an ISA cap, a fusion turned off). Every row a result file keeps carries it as ``run``."""
    import jaxlib
    import numpy

    from .._version import __version__

    return {"date": datetime.now(timezone.utc).isoformat(timespec="seconds"), "commit": _commit(), "machine": _cpu(),
            "devices": sorted({f"{d.platform}:{d.device_kind}" for d in jax.devices()}),
            "command": command or command_line(), "versions": {"jskel": __version__, "jax": jax.__version__,
            "jaxlib": jaxlib.__version__, "numpy": numpy.__version__, "python": platform.python_version()},
            **({"xla_flags": os.environ["XLA_FLAGS"]} if os.environ.get("XLA_FLAGS") else {})}


class JsonLines:
    """Rows printed as JSON lines as they are measured and, with ``out``, appended to that file
    (emptied first), so an interrupted benchmark keeps the rows it measured. Each row the file
    keeps carries the run's :func:`provenance` as ``run`` (docs/results.md shows it)."""

    def __init__(self, out=None, command: str | None = None):
        self.out = None if out is None else Path(out)
        self.run = None
        if self.out is not None:
            self.run = provenance(command)  # before the file is emptied: a tracked result file is not a change of the code
            self.out.parent.mkdir(parents=True, exist_ok=True)
            self.out.write_text("")

    def __call__(self, row: dict, keep: bool = True):
        """Print ``row``; also append it to ``out`` (with ``run``) unless ``keep`` is False (a log line)."""
        print(json.dumps(row), flush=True)
        if keep and self.out is not None:
            with self.out.open("a") as f:
                f.write(json.dumps({**row, "run": self.run}) + "\n")
