"""Benchmark result files as the docs show them: the latest run of each, with its provenance.

``python -m jskel bench FILE --out X.jsonl`` writes one JSON line per measurement and empties
the file first, so a file holds one run; every row it keeps carries that run's
``files.provenance`` as ``run`` (date, commit, machine, devices, command, versions). Rows
written before rows carried it are identified by the commit that last changed the file (its
date and hash, from git) and their own ``device``, ``jax`` and ``jskel`` keys, and by what git
history tells of them (:data:`HISTORY`: the commit whose code ran them, date, machine, command);
what neither records is said to be not recorded, never guessed. :func:`latest_run` picks a file's latest
run (should several runs have been appended to one file), :func:`markdown_table` renders rows,
:func:`provenance_line` says where a table comes from. docs/hooks/bench_results.py renders
them into docs/results.md and into the tables docs/performance.md marks.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path
from typing import NamedTuple

#: keys that identify a measurement rather than vary within one (shown in its provenance)
PROVENANCE_KEYS = ("run", "device", "jax", "jskel")

#: beside the result files: where rows written before they carried ``run`` came from (git history)
HISTORY = "result_files_history.json"


class Run(NamedTuple):
    """One run of a result file: its provenance (``run`` of its rows, or None where the rows
    do not carry one) and its rows, in file order."""

    provenance: dict | None
    rows: list[dict]


def read_rows(path) -> list[dict]:
    """A result file's rows (JSON lines; blank lines skipped); ValueError naming the file and
    line of one that is not a JSON object."""
    rows = []
    for i, line in enumerate(Path(path).read_text(encoding="utf-8").splitlines(), 1):
        if not line.strip():
            continue
        try:
            row = json.loads(line)
        except json.JSONDecodeError as e:
            raise ValueError(f"{path}:{i}: not a JSON line ({e.msg})") from None
        if not isinstance(row, dict):
            raise ValueError(f"{path}:{i}: not a JSON object (got {type(row).__name__})")
        rows.append(row)
    return rows


def latest_run(rows: list[dict]) -> Run:
    """The rows of the latest run: those whose ``run.date`` is the latest; rows without a
    ``run`` are one run of unknown date, older than any dated one."""
    dated = [r for r in rows if isinstance(r.get("run"), dict) and r["run"].get("date")]
    if not dated:
        return Run(None, rows)
    last = max(r["run"]["date"] for r in dated)
    mine = [r for r in dated if r["run"]["date"] == last]
    return Run(mine[0]["run"], mine)


def committed(path) -> tuple[str, str] | None:
    """(date, short hash) of the last commit that changed ``path``; None where git has none."""
    p = Path(path).resolve()
    try:
        out = subprocess.run(["git", "log", "-1", "--format=%cs %h", "--", p.name], cwd=p.parent,
                             capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.SubprocessError):
        return None
    parts = out.stdout.split()
    return (parts[0], parts[1]) if out.returncode == 0 and len(parts) == 2 else None


def _values(rows: list[dict], key: str) -> list:
    return list(dict.fromkeys(json.dumps(r[key], sort_keys=True) for r in rows if key in r))


def provenance_line(path, run: Run, name: str | None = None) -> str:
    """Markdown: which file, the command, the machine, the date and commit and the versions of
    ``run`` (what the rows do not record is said so)."""
    p = run.provenance
    name = name or Path(path).name
    devices = [json.loads(v) for v in _values(run.rows, "device")]
    if p is not None:
        versions = ", ".join(f"{k} {v}" for k, v in p.get("versions", {}).items())
        when = f"{p['date']}, commit `{p.get('commit') or 'not recorded'}`"
        return (f"`{name}`, written by `{p.get('command', 'a command not recorded')}` on {p.get('machine', 'a machine not recorded')} "
                f"({', '.join(p.get('devices', devices))}), {when}; {versions}.")
    c = committed(path)
    when = f"committed {c[0]} in `{c[1]}`" if c else "not committed"
    versions = ", ".join(f"{k} {', '.join(json.loads(v) for v in _values(run.rows, k))}" for k in ("jax", "jskel")
                         if _values(run.rows, k))
    h = history(path)
    told = "" if h is None else (
        f" From git history ({HISTORY}): run {h['date']} on the code of commit `{h['commit']}`, on {h['machine']}, "
        f"by `{h['command']}`" + (f" ({h['note']})" if h.get("note") else "") + ".")
    return (f"`{name}`, {when}; command and machine not recorded in the file (device "
            f"{', '.join(d for d in devices if d) or 'not recorded'}); {versions or 'versions not recorded'}.{told}")


def history(path) -> dict | None:
    """What git history says of a result file whose rows carry no ``run``: its entry (``commit``
    whose code ran the rows, ``date``, ``machine``, ``command``, optional ``note``) in
    :data:`HISTORY` beside it; None where there is none."""
    f = Path(path).parent / HISTORY
    if not f.is_file():
        return None
    return json.loads(f.read_text(encoding="utf-8"))["files"].get(Path(path).name)


def cell(value) -> str:
    """A value as a table cell: integers with thousands separators, floats to four significant
    digits, a setting as ``key=value`` pairs, nothing for a missing value."""
    if value is None:
        return ""
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, int):
        return f"{value:,}"
    if isinstance(value, float):
        return f"{value:,.0f}" if abs(value) >= 1e4 else f"{value:.4g}"
    if isinstance(value, dict):
        text = ", ".join(f"{k}={json.dumps(v)}" for k, v in value.items())
    else:
        text = value if isinstance(value, str) else json.dumps(value)
    return text.replace("|", "&#124;").replace("\n", " ")


def varying_keys(rows: list[dict]) -> tuple[list[str], dict]:
    """(keys whose value differs between rows or is missing from some, in order of first
    appearance; {key: value} of the keys every row has with one value), provenance keys apart."""
    keys = [k for k in dict.fromkeys(k for r in rows for k in r) if k not in PROVENANCE_KEYS]
    same = {k: rows[0][k] for k in keys if all(k in r for r in rows) and len(_values(rows, k)) == 1}
    return [k for k in keys if k not in same], same


def row_groups(rows: list[dict]) -> list[list[dict]]:
    """Rows grouped by the keys they have (a peer's rows, an animated scene's frame rows and
    the renders' rows each have their own), groups in order of first appearance."""
    groups: dict[frozenset, list[dict]] = {}
    for r in rows:
        groups.setdefault(frozenset(r), []).append(r)
    return list(groups.values())


def markdown_table(rows: list[dict], columns: list[str]) -> str:
    """A Markdown table of ``columns`` (headers are the keys) over ``rows``; numeric columns
    aligned right."""
    def numeric(k):
        vals = [r[k] for r in rows if r.get(k) is not None]
        return bool(vals) and all(isinstance(v, (int, float)) and not isinstance(v, bool) for v in vals)

    head = "| " + " | ".join(f"`{k}`" for k in columns) + " |"
    rule = "| " + " | ".join("---:" if numeric(k) else "---" for k in columns) + " |"
    return "\n".join([head, rule] + ["| " + " | ".join(cell(r.get(k)) for k in columns) + " |" for r in rows])


def matches(row: dict, filters: dict) -> bool:
    """Whether ``row`` has every ``key: value`` of ``filters`` (a value ``-``: the key is absent)."""
    for k, v in filters.items():
        if v == "-":
            if k in row:
                return False
        elif k not in row or (row[k] != v and str(row[k]) != str(v)):
            return False
    return True
