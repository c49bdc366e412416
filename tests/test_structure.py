"""The package's shape, checked from its source: one declared interface, one registry.

* nothing asks a representation what it has (``hasattr``): the interface declares every member;
* no representation's type name appears as a string outside its own folder and the registry
  (the renderer, the benches and the CLI talk to the interface, so a new representation is a
  folder and a registry line);
* no module imports another folder's private module (``from ..frusta._scene import ...``);
* every registered representation is a final subclass of the interface's base with its name;
* config/ imports nothing of the package above it (only itself and the registry, whose
  representations' sections it validates);
* measure/ (the harness) and peers/ (Embree, Mitsuba, marching cubes) import neither the other:
  what both use is in probe/, and the CLI hands the peers to the harness;
* no dated measurement sits in the package's source: figures that chose a constant or a code
  path live in docs/choices.md and the result files, where they are rerun and replaced;
* no machine is named in the package's source (``2-core``, ``H100``, ``EPYC``, ...): a figure
  measured on one lives, with its machine, in docs/choices.md (measure/files.py's CPU-model
  format example aside);
* no import runs back up: the package's import graph (imports inside functions counted) has no
  cycle, so its modules stand in floors;
* an experiment reaches the code as one value (``config.Experiment``, a scene of one where a
  file says ``object:``): no ``is_scene``, no ``single`` switch, no ``(exp, obj)`` pair, in the
  package, the tests or the notebooks.
"""

from __future__ import annotations

import ast
import re
from pathlib import Path

from jskel import registry
from jskel.interface import Representation

PKG = Path(__file__).resolve().parent.parent / "jskel"


def _sources():
    return sorted(p for p in PKG.rglob("*.py"))


def _folder(p: Path) -> str | None:
    rel = p.relative_to(PKG).parts
    return rel[0] if len(rel) > 1 else None


def test_nothing_asks_a_representation_what_it_has():
    found = []
    for p in _sources():
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "hasattr":
                found.append(f"{p.relative_to(PKG)}:{node.lineno}")
    assert found == [], found


def test_no_representation_is_named_outside_its_folder_and_the_registry():
    """String constants equal to a registered name, anywhere in the package outside that
    representation's folder and the registry. A keyword argument's value is another API's
    vocabulary (``trimesh.load(path, force="mesh")``) and is not counted."""
    names = set(registry.names())
    found = []
    for p in _sources():
        if p.name == "registry.py" and _folder(p) is None:
            continue
        tree = ast.parse(p.read_text())
        keyword_values = {id(k.value) for node in ast.walk(tree) if isinstance(node, ast.Call) for k in node.keywords}
        for node in ast.walk(tree):
            if (isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names
                    and _folder(p) != node.value and id(node) not in keyword_values):
                found.append(f"{p.relative_to(PKG)}:{node.lineno}: {node.value!r}")
    assert found == [], found


def test_no_folder_imports_another_folders_private_module():
    found = []
    for p in _sources():
        here = _folder(p)
        for node in ast.walk(ast.parse(p.read_text())):
            if not isinstance(node, ast.ImportFrom) or node.module is None:
                continue
            mod = node.module.split(".")
            if node.level == 0 and mod[0] == "jskel":
                mod = mod[1:]
            elif node.level == 0:
                continue
            elif node.level == 1 and here is not None:  # a sibling module of the same folder
                continue
            target = mod[0] if mod else None
            if any(part.startswith("_") and not part.startswith("__") for part in mod[1:]) and target != here:
                found.append(f"{p.relative_to(PKG)}:{node.lineno}: from {'.' * node.level}{node.module}")
    assert found == [], found


def test_every_registered_representation_is_a_final_subclass_of_the_base():
    for name in registry.names():
        rep = registry.get(name)
        assert isinstance(rep, Representation), name
        assert rep.name == name
        assert getattr(type(rep), "__final__", False), f"{name}: mark the class typing.final"
        assert rep.Config.model_fields["type"].annotation.__args__ == (name,)


# the fit is the frusta's fitter (Bhagvat et al.'s skeleton, fitted to point clouds): it works on
# frusta params by design, so it may name their classes
NAMES_CLASSES_OF = {"fit": {"frusta"}}


def _class_names(name: str) -> set[str]:
    import importlib

    mod = importlib.import_module(f"jskel.{name}")
    return {n for n in getattr(mod, "__all__", ()) if isinstance(getattr(mod, n, None), type)}


def test_no_representation_class_is_used_outside_its_folder():
    """A representation's classes (its package's exported types: its config, params, payload)
    imported (``from ..frusta import FrustaConfig``) or read as an attribute (``frusta.FrustaConfig``)
    outside its folder: the CLI, the benches and the peers ask the interface instead
    (``Representation.skeleton``, ``export_mesh``, ``animated``)."""
    classes = {name: _class_names(name) for name in registry.names()}
    found = []
    for p in _sources():
        here = _folder(p)
        allowed = NAMES_CLASSES_OF.get(here, set()) | {here}
        for node in ast.walk(ast.parse(p.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module is not None:
                target = node.module.split(".")[-1]
                if target in classes and target not in allowed:
                    found += [f"{p.relative_to(PKG)}:{node.lineno}: {a.name}" for a in node.names if a.name in classes[target]]
            elif (isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in classes
                  and node.value.id not in allowed and node.attr in classes[node.value.id]):
                found.append(f"{p.relative_to(PKG)}:{node.lineno}: {node.value.id}.{node.attr}")
    assert found == [], found


def test_animated_is_declared_where_a_section_has_a_frame():
    """``Representation.animated`` (what ``--frames`` and a scene's ``frame`` ask) is declared by
    exactly the representations whose sections have a ``frame`` field (:meth:`at_frame` sets it)."""
    for name in registry.names():
        rep = registry.get(name)
        assert rep.animated == ("frame" in rep.Config.model_fields), name


def test_no_dated_measurement_is_left_in_the_source():
    """No ``YYYY-MM-DD`` date in any module of the package (comments and docstrings included):
    a measurement that chose something is recorded in docs/choices.md with its date, commit and
    machine, and the code points there. The pattern is checked to find a date."""
    date = re.compile(r"\b20\d\d-[01]\d-[0-3]\d\b")
    assert date.search("# took 1.2 s (one-off, 2026-12-06, 2-core Xeon)")
    found = [f"{p.relative_to(PKG.parent)}:{i}" for p in _sources() for i, line in enumerate(p.read_text().splitlines(), 1) if date.search(line)]
    assert not found, found
    choices = (PKG.parent / "docs" / "choices.md").read_text()
    anchors = {m.group(1) for m in re.finditer(r"^### (\S+)$", choices, re.M)}
    cited = {m.group(1) for p in _sources() for m in re.finditer(r"docs/choices\.md#([\w-]+)", p.read_text())}
    assert cited and cited <= anchors, sorted(cited - anchors)


def test_no_machine_figure_is_left_in_the_source():
    """No machine named in any module of the package (comments and docstrings included; a CPU
    or accelerator model, or a core count such as "2 cores"): a figure measured on a machine is
    recorded in docs/choices.md with that machine, and the code states the choice in words and
    points there. Only measure/files.py names a CPU model, as the example of the format it
    writes. The pattern is checked to find a machine."""
    machine = re.compile(r"2-core|[0-9]+ cores|H100|H200|EPYC|Xeon")
    assert machine.search("# took 0.10 s on the H100") and machine.search("(1024x768, 2-core CPU)")
    assert machine.search("40 s of XLA compile on 2 cores") and not machine.search("one device per core")
    allowed = {PKG / "measure" / "files.py"}
    found = [f"{p.relative_to(PKG.parent)}:{i}: {line.strip()}" for p in _sources() if p not in allowed
             for i, line in enumerate(p.read_text().splitlines(), 1) if machine.search(line)]
    assert not found, found


def _imported(p: Path) -> set[str]:
    """The package modules a source file imports anywhere in it (functions included), relative
    imports resolved: ``from .. import registry`` in jskel/config/_load.py is ``jskel.registry``."""
    mod = ["jskel", *p.relative_to(PKG).with_suffix("").parts]
    if mod[-1] == "__init__":
        mod = mod[:-1]
    pkg = mod if p.name == "__init__.py" else mod[:-1]
    out = set()
    for node in ast.walk(ast.parse(p.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.split(".")[0] == "jskel"}
        elif isinstance(node, ast.ImportFrom):
            base = pkg[: len(pkg) - node.level + 1] if node.level else []
            name = ".".join(base + ([node.module] if node.module else []))
            if name.split(".")[0] != "jskel":
                continue
            out |= {f"{name}.{a.name}" for a in node.names} if not node.module else {name}
    return out


def test_config_imports_nothing_above_it():
    """jskel/config/ validates files; what runs them (render, measure, fit, the CLI) imports it,
    never the reverse. Its modules import only jskel.config and jskel.registry (the resolver
    checked to see ``from .. import registry``)."""
    allowed = ("jskel.config", "jskel.registry")
    bad = {str(p.relative_to(PKG.parent)): sorted(m for m in _imported(p) if not m.startswith(allowed))
           for p in sorted((PKG / "config").glob("*.py"))}
    assert "jskel.registry" in _imported(PKG / "config" / "_load.py")
    bad = {k: v for k, v in bad.items() if v}
    assert not bad, bad


def test_measure_and_peers_import_neither_the_other():
    """The harness (jskel/measure/) and the peers (jskel/peers/) share jskel/probe/ (timing, the
    cast timed alone, metrics, the study protocol) and import neither the other; the CLI passes
    ``jskel.peers.PEERS`` to the harness's commands."""
    pairs = [("measure", "jskel.peers"), ("peers", "jskel.measure")]
    bad = {str(p.relative_to(PKG.parent)): sorted(m for m in _imported(p) if m.startswith(other))
           for folder, other in pairs for p in sorted((PKG / folder).glob("*.py"))}
    bad = {k: v for k, v in bad.items() if v}
    assert not bad, bad
    assert "jskel.probe.timing" in _imported(PKG / "peers" / "skeleton_study.py")  # the resolver sees them


def test_a_representation_missing_members_is_refused_when_its_class_is_defined():
    """A subclass of the interface's base that lacks what it must give is a TypeError when the
    class statement runs (not at its first call), naming every missing member at once; its
    Config must be a model whose ``type`` is ``Literal[name]``. One that gives them all (the
    rest inherited) is accepted."""
    from typing import Literal

    import pytest
    from pydantic import BaseModel

    with pytest.raises(TypeError) as e:
        class _Half(Representation):
            name = "half"

            def build(self, cfg, dtype=None):
                return None
    msg = str(e.value)
    assert all(m in msg for m in ("Config", "intersect_one", "albedo", "inside")) and "build" not in msg.replace("jskel", "")

    class _Cfg(BaseModel):
        type: Literal["other"]

    with pytest.raises(TypeError, match=r"Config \(a pydantic model whose type is Literal\['whole'\]\)"):
        class _Mislabelled(Representation):
            name, Config = "whole", _Cfg
            build = intersect_one = albedo = inside = staticmethod(lambda *a: None)

    class _WholeCfg(BaseModel):
        type: Literal["whole"]

    class _Whole(Representation):
        name, Config = "whole", _WholeCfg
        build = intersect_one = albedo = inside = staticmethod(lambda *a: None)

    assert _Whole.cast is Representation.cast  # the optional members inherited


def _module_name(p: Path) -> str:
    mod = ["jskel", *p.relative_to(PKG).with_suffix("").parts]
    return ".".join(mod[:-1] if mod[-1] == "__init__" else mod)


def _import_graph() -> dict[str, set[str]]:
    """Module -> the package modules it imports (anywhere in it), each import resolved to the
    longest module name it starts with (``jskel.frusta.ReliefMaps`` is ``jskel.frusta``)."""
    mods = {_module_name(p): p for p in _sources()}

    def resolve(name: str) -> str | None:
        parts = name.split(".")
        return next((".".join(parts[:k]) for k in range(len(parts), 0, -1) if ".".join(parts[:k]) in mods), None)

    return {m: {r for r in map(resolve, _imported(p)) if r is not None and r != m} for m, p in mods.items()}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan, iterative)."""
    index, low, stack, on, out, counter = {}, {}, [], set(), [], [0]
    for root in graph:
        if root in index:
            continue
        work = [(root, iter(sorted(graph[root])))]
        index[root] = low[root] = counter[0]
        counter[0] += 1
        stack.append(root)
        on.add(root)
        while work:
            v, it = work[-1]
            w = next(it, None)
            if w is not None:
                if w not in index:
                    index[w] = low[w] = counter[0]
                    counter[0] += 1
                    stack.append(w)
                    on.add(w)
                    work.append((w, iter(sorted(graph[w]))))
                elif w in on:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on.discard(w)
                    comp.append(w)
                    if w == v:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def test_no_import_runs_back_up():
    """No module imports one that imports it back, directly or through others, imports inside
    functions included: the graph is acyclic, so every module sits on a floor above what it
    imports. (The cycle finder is checked on a graph with one.)"""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
    graph = _import_graph()
    assert "jskel.frusta._relief" in graph["jskel.frusta._relief_method"]  # the resolver sees the package's modules
    assert not _cycles(graph), _cycles(graph)


_TWO_SHAPES = {"is_scene", "single", "build_single", "render_scene"}


def _two_shapes(p: Path) -> list[str]:
    """Where ``p`` still carries an experiment in two shapes: a name or attribute ``is_scene``,
    ``single``, ``build_single`` or ``render_scene``, or an ``(exp, obj)`` pair (assigned,
    unpacked in a loop, or taken as a function's first two parameters), or ``load(...)`` /
    ``validate(...)`` indexed or unpacked with ``*`` as if they returned one."""
    found = []
    for node in ast.walk(ast.parse(p.read_text())):
        name = (node.attr if isinstance(node, ast.Attribute) else node.id if isinstance(node, ast.Name)
                else node.arg if isinstance(node, (ast.arg, ast.keyword)) else None)
        if name in _TWO_SHAPES:
            found.append(f"{p.name}:{node.lineno}: {name}")
        targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(node, (ast.For, ast.comprehension)) else []
        for t in targets:
            if isinstance(t, ast.Tuple) and [getattr(e, "id", None) for e in t.elts[:2]] == ["exp", "obj"]:
                found.append(f"{p.name}:{getattr(node, 'lineno', t.lineno)}: (exp, obj)")
        if isinstance(node, (ast.FunctionDef, ast.Lambda)) and [a.arg for a in node.args.args[:2]] == ["exp", "obj"]:
            found.append(f"{p.name}:{node.lineno}: def (exp, obj)")
        if isinstance(node, (ast.Subscript, ast.Starred)) and isinstance(node.value, ast.Call):
            f = node.value.func
            if (f.attr if isinstance(f, ast.Attribute) else getattr(f, "id", None)) in ("load", "validate"):
                found.append(f"{p.name}:{node.lineno}: a pair taken from {ast.unparse(f)}(...)")
    return found


def test_an_experiment_reaches_the_code_as_one_value():
    """``config.load`` returns one ``Experiment``; nothing forks on ``is_scene`` or a ``single``
    switch, and no ``(exp, obj)`` pair is passed around, in the package, the tests or the
    notebooks' sources. (The finder is checked on a snippet that has each.)"""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        bad = Path(tmp) / "bad.py"
        bad.write_text("exp, obj = load(p)\nif exp.is_scene: pass\ndef f(exp, obj): return g(single=True)\n"
                       "r = render(*validate(raw)); o = config.load(p)[1]\n")
        assert len(_two_shapes(bad)) == 6, _two_shapes(bad)
    root = PKG.parent
    files = _sources() + sorted((root / "tests").rglob("*.py")) + sorted((root / "notebooks").glob("*.py"))
    found = [f for p in files if p.name != "test_structure.py" for f in _two_shapes(p)]
    assert not found, found
