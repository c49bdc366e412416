"""A sweep's results: ``results.csv`` (one row per setting, appended as rows finish, read back
to resume) and ``report.md`` (the sweep, the environment, the plot, the table).

Nothing is reported that was not measured in this run or read back from ``results.csv``.
"""

from __future__ import annotations

import csv
import platform
from pathlib import Path

import jax


def number(x):
    """A results-file cell as a float (None where empty or not a number)."""
    try:
        return float(x)
    except (TypeError, ValueError):
        return None


def read_done(path: Path) -> dict[str, dict]:
    """Rows of an existing ``results.csv`` by setting key (an interrupted sweep's work)."""
    if not path.exists():
        return {}
    with path.open(newline="") as f:
        return {row["setting"]: row for row in csv.DictReader(f)}


def columns(sweep, keys: list[str]) -> list[str]:
    """The columns of results.csv: varied keys, peer columns, timings (with the programs a
    setting's measurement, its reference's render included, handed to XLA or read back:
    ``sweep.programs_since``), metrics, environment."""
    peer = ["peer.level", "triangles", "peer_build_s"] if sweep.peer else []
    return (keys + peer + ["compile_s", "compiled", "loaded", "executables_loaded", "time_median_s", "time_min_s", "time_max_s", "runs", "rays", "rays_per_s"]
            + list(sweep.metrics) + ["hit_fraction", "device", "jax", "dtype", "setting"])


def equal_error(rows: list[dict], metric: str) -> list[dict]:
    """For each jskel row, the peer row with the fewest triangles whose ``metric`` and hit/miss
    disagreement are both at most jskel's (Fig. 6's "similar quality"), or None."""
    peers = sorted((r for r in rows if str(r.get("peer.level", "")) != ""), key=lambda r: int(r["triangles"]))
    out = []
    for r in rows:
        if str(r.get("peer.level", "")) != "" or number(r.get(metric)) is None:
            continue
        match = next((p for p in peers if number(p.get(metric)) is not None and number(p[metric]) <= number(r[metric])
                      and number(p.get("hit_miss_pct", 0)) <= number(r.get("hit_miss_pct", 0))), None)
        out.append({"setting": r["setting"], "error": number(r[metric]), "time_s": number(r["time_median_s"]),
                    "triangles": None if match is None else int(match["triangles"]),
                    "peer_time_s": None if match is None else number(match["time_median_s"])})
    return out


def cell(v):
    if isinstance(v, float):
        return f"{v:.6g}"
    return "" if v is None else v


def write_report(sweep, rows: list[dict], keys: list[str], path: Path, plot, run: dict | None = None):
    """report.md: the sweep's file, environment (``run``: ``files.provenance``, the command,
    machine, date, commit and versions), a table of every setting and the plot."""
    cols = keys + ["time_median_s", "time_min_s", "time_max_s", "compile_s"] + list(sweep.metrics)
    lines = [f"# Sweep of {sweep.base}", "",
             f"Varied: {', '.join(keys)}. Reference: {', '.join(sweep.reference) if sweep.reference else 'none'}. "
             f"Timing: median of {sweep.runs} warm runs after {sweep.warmup} warm-up, compile apart"
             + (f"; {sweep.parallel} worker processes shared the machine." if sweep.parallel > 1 else "."),
             f"Device: {rows[0].get('device', '?') if rows else '?'}; jax {jax.__version__}; Python {platform.python_version()}; "
             f"{platform.machine()}.", ""]
    if run is not None:
        lines[-1:-1] = [f"Written {run['date']} at commit {run.get('commit') or '(not recorded)'} by `{run['command']}` on "
                        f"{run['machine']}; " + ", ".join(f"{k} {v}" for k, v in run["versions"].items()) + "."]
    if plot is not None:
        lines += [f"![{sweep.metrics[0]} against time]({Path(plot).name})", ""]
    if sweep.peer is not None:
        cols = keys + ["peer.level", "triangles"] + cols[len(keys):]
    lines += ["| " + " | ".join(c.split(".")[-1] if c != "peer.level" else "mesh level" for c in cols) + " |",
              "| " + " | ".join("---" for _ in cols) + " |"]
    for r in rows:
        lines.append("| " + " | ".join(str(r.get(c, "")) for c in cols) + " |")
    if sweep.peer is not None:
        m = sweep.metrics[0]
        lines += ["", f"Equal error (Fig. 6): the smallest mesh whose {m} and hit/miss % are at most the setting's.", "",
                  f"| setting | {m} | time s | mesh triangles | Embree cast s |", "| --- | --- | --- | --- | --- |"]
        for e in equal_error(rows, m):
            tri = "none up to the largest level" if e["triangles"] is None else f"{e['triangles']:,}"
            pt = "" if e["peer_time_s"] is None else f"{e['peer_time_s']:.4g}"
            lines.append(f"| {e['setting']} | {e['error']:.4g} | {e['time_s']:.4g} | {tri} | {pt} |")
    path.write_text("\n".join(lines) + "\n")
    return path
