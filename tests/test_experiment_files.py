"""Every file in ``experiments/`` validates as the command it is written for, and says that
command: a render experiment through ``jskel.load``, a bench's scenes and settings, a sweep's
settings and references, a fit, the fit and latency benches, each through the reader the CLI
uses (no build, nothing compiled). Its comment names ``python -m jskel <command>
experiments/<its name>``, so a reader knows how to run it. Float64 requests are recorded, not
switched on (the test workers stay in float32)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from jskel.config import load
from jskel.config import _load as config_load
from jskel.measure import files

ROOT = Path(__file__).resolve().parent.parent
FILES = sorted((ROOT / "experiments").glob("*.yaml"))


def kind_of(raw: dict) -> str:
    """The command a file is for, from its top-level keys (as ``jskel bench`` dispatches)."""
    if "latency" in raw or "fit" in raw or "fit_real" in raw or "fit_trees" in raw or "scenes" in raw:
        return "bench"
    if "base" in raw:
        return "sweep"
    if "points" in raw:
        return "fit"
    return "render"


def validate_file(path: Path, kind: str, raw: dict) -> int:
    """Validate ``path`` as the CLI reads it; returns how many experiments it names."""
    from jskel.fit import FitBenchFile, FitFile
    from jskel.measure.bench import BenchFile, groups_of
    from jskel.measure.latency import LatencyFile
    from jskel.measure.sweep import load_sweep

    if kind == "render":
        load(path)
        return 1
    if kind == "fit":
        files.read_model(FitFile, path, [])
        return 1
    if kind == "sweep":
        _, jobs, refs = load_sweep(path, [])
        return len(jobs) + sum(r is not None for r in refs)
    if "fit" in raw:
        files.read_model(FitBenchFile, path, [])
        return 1
    if "fit_trees" in raw:
        from jskel.fit import TreeBenchFile

        b = files.read_model(TreeBenchFile, path, []).fit_trees
        return len(b.iterations) + len(b.segments)
    if "fit_real" in raw:  # the model the CLI's peers hand the harness (its packages imported only when it runs)
        from jskel.peers.skeletonizer import RealFitBenchFile

        return len(files.read_model(RealFitBenchFile, path, []).fit_real.meshes)
    if "latency" in raw:
        lat = files.read_model(LatencyFile, path, []).latency
        for i, name in enumerate(lat.gallery):
            load(files.beside(name, path, f"latency.gallery[{i}]"), list(lat.set))
        return len(lat.gallery)
    return sum(len(g.jobs) for g in groups_of(files.read_model(BenchFile, path, []), path, []))


def test_the_folder_holds_every_kind():
    kinds = {kind_of(yaml.safe_load(p.read_text())) for p in FILES}
    assert kinds == {"render", "bench", "sweep", "fit"} and len(FILES) >= 60


@pytest.mark.parametrize("path", FILES, ids=[p.stem for p in FILES])
def test_each_experiment_file_validates_and_names_its_command(path, monkeypatch):
    asked = []
    monkeypatch.setattr(config_load, "_enable_x64_if_asked", lambda exp: asked.append(exp))
    raw = yaml.safe_load(path.read_text())
    kind = kind_of(raw)
    assert validate_file(path, kind, raw) >= 1
    comment = "\n".join(line for line in path.read_text().splitlines() if line.startswith("#"))
    named = re.findall(r"python -m jskel (\w+) experiments/([\w.]+\.yaml)", comment)
    assert (kind, path.name) in named, f"{path.name}: its comment does not say 'python -m jskel {kind} experiments/{path.name}'"
