"""mkdocs hook: docs/config.md, the configuration reference, generated from the pydantic models
at every build (:func:`config_files`, here, and ``jskel.config.reference_rows``), so it cannot
drift from the code. A key without a description fails the build. The list of file models is
kept here, in the docs build, not in ``jskel.config``: it names the fit's, the benchmarks' and the
sweeps' models, which sit above the config floor."""

from __future__ import annotations

import re
from typing import NamedTuple

from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File
from pydantic import BaseModel

from jskel.config import reference_rows, undocumented


class ConfigFile(NamedTuple):
    """A file (or section) the project reads: a title, the command that reads it, the model of
    its top level and the dotted prefix its keys carry (``object.`` for a representation)."""

    title: str
    command: str
    model: type[BaseModel]
    prefix: str


def config_files() -> list[ConfigFile]:
    """Every configuration file's model: the experiment, each registered representation's
    ``object`` section (also a scene object's ``shape``), the fit, bench, fitting bench,
    latency and sweep files."""
    from jskel import registry
    from jskel.config import ExperimentFile
    from jskel.fit import FitBenchFile, FitFile
    from jskel.measure.bench import BenchFile
    from jskel.measure.latency import LatencyFile
    from jskel.measure.sweep import SweepFile

    out = [ConfigFile("Experiment", "python -m jskel render EXP", ExperimentFile, "")]
    out += [ConfigFile(f"object: type {n}", "python -m jskel render EXP", registry.get(n).Config, "object.")
            for n in registry.names()]
    return out + [
        ConfigFile("Fit file", "python -m jskel fit FILE", FitFile, ""),
        ConfigFile("Bench file", "python -m jskel bench FILE", BenchFile, ""),
        ConfigFile("Fitting bench file", "python -m jskel bench FILE", FitBenchFile, ""),
        ConfigFile("Latency bench file", "python -m jskel bench FILE", LatencyFile, ""),
        ConfigFile("Sweep file", "python -m jskel sweep FILE", SweepFile, ""),
    ]

INTRO = """# Configuration reference

Every key of every file jskel reads, generated from the pydantic models when this site is built
(`docs/hooks/config_reference.py` renders `jskel.config.reference_rows`), so it says what the code
accepts. The meaning of a key is the description under its field in the model; a key without one
fails the docs build. A key not listed here is an error when a file is read, as are a wrong type,
a value outside its range, NaN and infinity: every problem of a file is reported at once, a line
each naming the key (the commands exit with status 2).

Paths are dotted; `[]` marks the items of a list (`lights[].color`), `<key>` a mapping's values.
Types are written as in YAML: `[float, float, float]` is a list of three numbers, a quoted word
is one of the accepted values, a *section* has the keys listed under it. Defaults are JSON
(YAML's flow style); `required` keys have none.
"""


def _cell(text: str) -> str:
    """Table cell text: RST double backticks as Markdown code, no pipes that would split it."""
    return re.sub(r"``(.+?)``", r"`\1`", text).replace("|", "&#124;")


def _code(text: str) -> str:
    return f"`{text}`" if text else ""


def _default(text: str) -> str:
    """A default as code where it is a value (JSON), as words where it says there is none or that
    a section's keys give it."""
    return f"*{text}*" if text == "required" or "defaults" in text else _code(text)


def page() -> str:
    """The whole page: a section per configuration file, a table row per key."""
    out, shown = [INTRO], {}
    for cf in config_files():
        rows = reference_rows(cf.model, cf.prefix, shown)
        where = f"`{cf.model.__module__.split('._')[0]}.{cf.model.__name__}`"
        out.append(f"\n## {cf.title}\n\nRead by `{cf.command}`; the model is {where}.\n")
        if cf.prefix == "object.":
            out.append("The same keys, without the `object.` prefix, make a scene object's `objects[].shape`.\n")
        out.append("| key | type | default | range | meaning |\n| --- | --- | --- | --- | --- |")
        out += [f"| `{r.path}` | {_cell(_code(r.type))} | {_cell(_default(r.default))} | {_cell(r.range)} | {_cell(r.description)} |"
                for r in rows]
    return "\n".join(out) + "\n"


def on_files(files, config):
    missing = [f"{cf.title}: {p}" for cf in config_files() for p in undocumented(cf.model, cf.prefix)]
    if missing:
        raise PluginError("configuration keys without a description (add a string literal under the field):\n  "
                          + "\n  ".join(missing))
    files.append(File.generated(config, "config.md", content=page()))
    return files
