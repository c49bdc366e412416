"""mkdocs hook: the benchmark result files under docs/ as the docs show them, generated at build.

docs/results.md gets every result file's latest run (``jskel.measure.result_files``): its
provenance (command, machine, date and commit, versions), the keys that are the same in every
row, and a table of the rest. A page marks a table to take from a result file with

    <!-- results FILE KEY KEY ... [KEY=VALUE ...] -->

(FILE relative to docs/; KEY a column; KEY=VALUE keeps the rows that have that value, KEY=- those
without the key); the marker becomes the table of the latest run and the line that says where
it comes from. An unknown file, a column no selected row has, or a selection of no rows fails
the build.

A sweep's report page (``sweep_*/report.md``, as ``jskel sweep`` wrote it) that does not name the
command which wrote it gets a line naming it and its result file (``sweep_relief_steps_cpu/`` is
``experiments/sweep_relief_steps.yaml``'s; a folder with no such experiment fails the build).
"""

from __future__ import annotations

import json
import posixpath
import re
import shlex
from pathlib import Path

from markdown.extensions.toc import slugify
from mkdocs.exceptions import PluginError
from mkdocs.structure.files import File

from jskel.measure.result_files import latest_run, markdown_table, matches, provenance_line, read_rows, row_groups, varying_keys


PAGE = "results.md"
MARKER = re.compile(r"<!--\s*results\s+(.+?)\s*-->")

INTRO = """# Result files

Every benchmark result file under `docs/`, generated from the files when this site is built
(`docs/hooks/bench_results.py`): the latest run of each, as `python -m jskel bench FILE --out
docs/NAME.jsonl` wrote it, with the command, machine, date, commit and versions that identify it.
The history of a file is its git log, not this page. A run records its provenance in every row
(`run`); rows written before they carried it are identified by the commit that last changed the
file, their own `device`, `jax` and `jskel` keys and what git history tells of them
(`docs/result_files_history.json`: the commit whose code ran them, date, machine, command). Keys with one value in every row are listed
above each table; the table holds the rest. [Performance](performance.md) explains the figures.
"""


def result_files(docs_dir) -> list[Path]:
    """The result files: every JSON-lines file directly under docs/."""
    return sorted(Path(docs_dir).glob("*.jsonl"))


def anchor(name: str) -> str:
    """The anchor of a result file's section on docs/results.md."""
    return slugify(name, "-")


def plots(path: Path) -> list[Path]:
    """The plots the bench wrote beside a result file (``NAME.png``, ``NAME_<scene>.png``), not
    those of another file whose name starts with this one's."""
    stems = [p.stem for p in result_files(path.parent)]
    return [p for p in sorted(path.parent.glob(f"{path.stem}*.png"))
            if max((s for s in stems if p.stem == s or p.stem.startswith(s + "_")), key=len, default=None) == path.stem]


def section(path: Path) -> str:
    run = latest_run(read_rows(path))
    cols, same = varying_keys(run.rows)
    out = [f"## {path.name}", "", f"From {provenance_line(path, run, f'docs/{path.name}')}", ""]
    pngs = plots(path)
    if pngs:
        out += ["Plotted by the same command beside it:", ""] + [f"![{p.name}]({p.name})" for p in pngs] + [""]
    if same:
        out += ["Every row: " + _pairs(same) + ".", ""]
    groups = row_groups(run.rows) if cols else []
    for rows in groups:
        mine, fixed = varying_keys(rows) if len(groups) > 1 and len(rows) > 1 else ([k for k in cols if any(k in r for r in rows)], {})
        fixed = {k: v for k, v in fixed.items() if k not in same}
        head = f"{len(rows)} row{'s' * (len(rows) > 1)}" + (", each with " + _pairs(fixed) if fixed else "")
        out += [head + ":", ""] if len(groups) > 1 else []
        out += [markdown_table(rows, mine) if mine else "", ""]
    return "\n".join(out)


def _pairs(values: dict) -> str:
    return "; ".join(f"`{k}` {json.dumps(v)}" for k, v in values.items())


def marked_table(spec: str, docs_dir, src_uri: str) -> str:
    """The table a marker asks for, with the line that says where it comes from."""
    tokens = shlex.split(spec)
    path = Path(docs_dir) / tokens[0]
    if not path.is_file():
        raise PluginError(f"{src_uri}: results marker names {tokens[0]!r}, which is not a file under docs/")
    filters = {}
    for t in tokens[1:]:
        if "=" in t:
            k, v = t.split("=", 1)
            try:
                filters[k] = json.loads(v) if v != "-" else v
            except json.JSONDecodeError:
                filters[k] = v
    cols = [t for t in tokens[1:] if "=" not in t]
    run = latest_run(read_rows(path))
    rows = [r for r in run.rows if matches(r, filters)]
    missing = [k for k in cols if not any(k in r for r in rows)]
    if not rows or missing:
        raise PluginError(f"{src_uri}: results marker {spec!r}: " + (f"no row has {missing}" if rows else "no row matches"))
    link = posixpath.relpath(PAGE, posixpath.dirname(src_uri) or ".") + "#" + anchor(path.name)
    where = provenance_line(path, run, f"docs/{path.name}")
    return f"{markdown_table(rows, cols)}\n\nLatest run of {where} [Every column]({link}).\n"


def on_files(files, config):
    docs = config["docs_dir"]
    text = INTRO + "".join("\n" + section(p) for p in result_files(docs))
    files.append(File.generated(config, PAGE, content=text))
    return files


SWEEP_REPORT = re.compile(r"(sweep_[^/]+)_[^_/]+/report\.md")


def sweep_command(markdown: str, src_uri: str) -> str:
    """A sweep report names its files under its ``Written ... by `command` `` line (the
    provenance ``jskel sweep`` writes); a report without that line fails the build, since no
    figure may stand without the command that produced it."""
    m = SWEEP_REPORT.fullmatch(src_uri)
    if m is None:
        return markdown
    written = re.search(r"^Written .* by `[^`]+`.*$", markdown, re.M)
    if written is None:
        raise PluginError(f"{src_uri}: no 'Written ... by `command`' line: rerun experiments/{m.group(1)}.yaml to write it")
    folder = posixpath.dirname(src_uri)
    line = (f"Its files, as the command wrote them, are in `docs/{folder}`: `results.csv` (a row per setting), "
            f"`pareto.png` and this report.")
    return markdown[:written.end()] + "\n\n" + line + markdown[written.end():]


def on_page_markdown(markdown, page, config, files):
    markdown = sweep_command(markdown, page.file.src_uri)
    return MARKER.sub(lambda m: marked_table(m.group(1), config["docs_dir"], page.file.src_uri), markdown)
