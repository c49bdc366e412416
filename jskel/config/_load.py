"""Experiment files in: YAML read, ``--set key.path=value`` overrides applied (parsed as YAML
scalars, before validation, so an override is checked like the file itself), then every
section validated with every bad key reported at once; and the resolved config out as plain
data for ``run.json``."""

from __future__ import annotations

import copy
from pathlib import Path

import yaml
from pydantic import BaseModel, ValidationError

from .. import registry
from ._errors import ConfigError, _format, _loc, _short
from ._schema import Experiment, ExperimentFile

DEFAULT_EXPERIMENT = Path(__file__).parent.parent / "data" / "default.yaml"


def _validate_shape(raw_obj: dict, where: tuple) -> tuple[BaseModel | None, list[str]]:
    kind = raw_obj.get("type")
    if kind not in registry.names():
        return None, [f"{_loc(where)}.type: unknown representation (got {_short(kind)}; known: {', '.join(registry.names())})"]
    try:
        return registry.get(kind).Config.model_validate(raw_obj), []
    except ValidationError as e:
        return None, _format(e, where)


def _shapes_validated(raw: dict) -> tuple[dict, list[str], list[str]]:
    """``raw`` with every object's section (``object``, ``objects[i].shape``) replaced by its
    representation's validated model, and the error lines of those that fail, named by their
    own key paths (``object.skeleton.radii[1]: ...``), and the paths of those (their lines are
    given once)."""
    raw, lines, failed = dict(raw), [], []
    raw_obj = raw.get("object")
    if isinstance(raw_obj, dict):
        obj, more = _validate_shape(raw_obj, ("object",))
        lines += more
        if obj is None:
            failed.append("object")
        else:
            raw["object"] = obj
    elif raw_obj is not None:
        lines.append(f"object: must be a mapping with a 'type' key (got {_short(raw_obj)})")
        failed.append("object")
    raw_objs = raw.get("objects")
    if isinstance(raw_objs, list):
        raw["objects"] = objs = list(raw_objs)
        for i, o in enumerate(raw_objs):
            shape = o.get("shape") if isinstance(o, dict) else None
            if isinstance(shape, dict):
                got, more = _validate_shape(shape, ("objects", i, "shape"))
                lines += more
                if got is None:
                    failed.append(f"objects[{i}].shape")
                else:
                    objs[i] = {**o, "shape": got}
    return raw, lines, failed


def validate(raw: dict) -> Experiment:
    """Validate a raw experiment dict (an ``object:`` file or a scene's ``objects:``) into the
    one :class:`Experiment` value (``ExperimentFile.experiment``: one object is a scene of one),
    or raise ConfigError with a line per problem, every section's at once."""
    if not isinstance(raw, dict):
        raise ConfigError([f"<root>: an experiment must be a mapping (got {_short(raw)})"])
    raw, shape_lines, failed = _shapes_validated(raw)
    lines: list[str] = []
    try:
        file = ExperimentFile.model_validate(raw)
    except ValidationError as e:  # the failed shapes have their lines already
        lines += [ln for ln in _format(e) if not any(ln.startswith(f) and ln[len(f)] in ".[:" for f in failed)]
        file = None
    if lines or shape_lines:
        raise ConfigError(lines + shape_lines)
    return file.experiment()


def set_path(d: dict, path: str, value):
    """Set the value at a dotted ``path`` of the raw experiment ``d`` in place (list indices
    allowed; missing mappings created): what a ``--set`` override and ``jskel.view`` write."""
    parts = path.split(".")
    cur = d
    for i, p in enumerate(parts[:-1]):
        if isinstance(cur, list):
            cur = cur[int(p)]
            continue
        if p not in cur or not isinstance(cur[p], (dict, list)):
            cur[p] = {}
        cur = cur[p]
    last = parts[-1]
    if isinstance(cur, list):
        cur[int(last)] = value
    else:
        cur[last] = value


def apply_overrides(raw: dict, overrides: list[str]) -> dict:
    """Return a copy of ``raw`` with ``key.path=value`` overrides applied (values parsed as YAML)."""
    out = copy.deepcopy(raw)
    for item in overrides:
        if "=" not in item:
            raise ConfigError([f"--set: expected key.path=value (got {item!r})"])
        key, val = item.split("=", 1)
        key = key.strip()
        if not key:
            raise ConfigError([f"--set: empty key (got {item!r})"])
        try:
            parsed = yaml.safe_load(val)
        except yaml.YAMLError as e:
            raise ConfigError([f"--set {key}: value is not valid YAML (got {val!r}): {e}"]) from None
        try:
            set_path(out, key, parsed)
        except (ValueError, IndexError, TypeError):
            raise ConfigError([f"--set {key}: no such list index in the experiment"]) from None
    return out


def read_yaml(path: str | Path | None) -> dict:
    """Read an experiment file (the embedded default when ``path`` is None)."""
    p = Path(path) if path is not None else DEFAULT_EXPERIMENT
    if not p.exists():
        raise ConfigError([f"experiment: file not found (got {str(p)!r})"])
    try:
        raw = yaml.safe_load(p.read_text())
    except yaml.YAMLError as e:
        raise ConfigError([f"experiment: {p} is not valid YAML: {str(e).splitlines()[0]}"]) from None
    return raw if raw is not None else {}


def load(path: str | Path | None = None, overrides: list[str] | None = None) -> Experiment:
    """Read an experiment file (None: the embedded default), apply ``key=value`` overrides and
    validate it (every bad key at once, a ``ConfigError``) into the one :class:`Experiment`
    value; the one loader of the CLI, the benchmarks, the sweeps and the notebooks. An
    experiment that asks for ``render.dtype: float64`` switches JAX's x64 on here, when it is
    read, before anything compiles (library code below never switches it)."""
    raw = apply_overrides(read_yaml(path), overrides or [])
    exp = validate(raw)
    _enable_x64_if_asked(exp)
    return exp


def _enable_x64_if_asked(exp: Experiment) -> None:
    """x64 on where the experiment asks for float64, at its loading, before anything compiles."""
    if exp.render.dtype == "float64":
        import jax

        jax.config.update("jax_enable_x64", True)


def resolved(exp: Experiment) -> dict:
    """The resolved config as plain data (saved to ``run.json``): the experiment as a scene,
    each object's shape as its representation's model dumps it; loading it renders the same."""
    return exp.model_dump(mode="json")
