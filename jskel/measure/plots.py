"""The measurements' plots: time per setting, error against time, cost against scene size.

Shared by ``jskel bench`` and ``jskel sweep``; each writes one PNG and returns its path, or None
when no row has what it plots. Matplotlib is imported on the first plot, with the non-interactive
Agg backend (importing this module changes no backend).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..probe.metrics import pareto_front
from .results import number


def _pyplot():
    """``matplotlib.pyplot`` on the Agg backend (files only, no display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def plot_bars(rows: list[dict], path: Path, title: str):
    """Warm median seconds per row as a bar chart (min-max as error bars), labelled by each
    row's ``label``; secondary rays per frame written over the bars where rows have them."""
    plt = _pyplot()
    if not rows:
        return None
    labels = [r.get("label") or str(r.get("setting")) for r in rows]
    med = [r["render_s_median"] for r in rows]
    lo = [m - r["render_s_min"] for m, r in zip(med, rows)]
    hi = [r["render_s_max"] - m for m, r in zip(med, rows)]
    fig, ax = plt.subplots(figsize=(max(6, 0.9 * len(rows)), 4.2))
    bars = ax.bar(range(len(rows)), med, yerr=[lo, hi], color="#4477aa", capsize=3)
    for b, r in zip(bars, rows):
        if r.get("secondary_rays") is not None:
            ax.annotate(f"{r['secondary_rays']:,}", (b.get_x() + b.get_width() / 2, b.get_height()), ha="center", va="bottom",
                        fontsize=7, xytext=(0, 2), textcoords="offset points")
    ax.set_xticks(range(len(rows)), labels, rotation=30, ha="right")
    ax.set_ylabel("warm median seconds per frame")
    ax.set_title(title + "\n(numbers: secondary rays per frame)" if any("secondary_rays" in r for r in rows) else title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def pareto_plot(t, e, labels: list[str], path: Path, ylabel: str, title: str, marked=None, marked_label: str = ""):
    """Error ``e`` against time ``t`` on log axes with the Pareto front marked, one label per
    point; ``marked`` (bool mask) points get an extra hollow marker (e.g. a peer's meshes).
    Shared by the bench and sweep commands."""
    plt = _pyplot()
    t, e = np.asarray(t, float), np.asarray(e, float)
    front = pareto_front(t, e)
    fig, ax = plt.subplots(figsize=(7, 5))
    ax.scatter(t[~front], e[~front], c="0.6", s=18, label="setting")
    order = np.argsort(t[front])
    ax.plot(t[front][order], e[front][order], "o-", c="C3", label="Pareto front")
    if marked is not None and np.any(marked):
        m = np.asarray(marked)
        ax.scatter(t[m], e[m], marker="^", facecolors="none", edgecolors="C0", s=40, label=marked_label)
    for lab, ti, ei in zip(labels, t, e):
        ax.annotate(lab, (ti, ei), fontsize=6, xytext=(2, 2), textcoords="offset points")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("warm median render time [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=8)
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path


def plot_sweep(rows: list[dict], keys: list[str], metric: str, path: Path, title: str):
    """A bench sweep's ``metric`` against warm median time (``pareto_plot``); None if no row
    has the metric."""
    ok = [r for r in rows if r.get(metric) is not None and r[metric] > 0]
    if not ok:
        return None
    labels = [",".join(str(r["setting"].get(k, "-")) for k in keys) for r in ok]
    title = title + "\nlabels: " + ", ".join(k.split(".")[-1] for k in keys) + " (- where a setting omits one)"
    return pareto_plot([r["render_s_median"] for r in ok], [r[metric] for r in ok], labels, path, metric, title)


def plot_scaling(rows: list[dict], path: Path, title: str):
    """Cost per ray and traversal work per ray against the number of primitives (log2 x axis,
    so growth in proportion to log(segments) is a straight line), from rows with ``stats``.
    The first swept key is the size axis; rows that differ in the other swept keys are drawn
    as separate lines (e.g. per-ray walks against packets)."""
    plt = _pyplot()
    ok = [r for r in rows if r.get("nodes_per_ray_mean") is not None]
    if len(ok) < 2:
        return None
    groups: dict[str, list[dict]] = {}
    for r in ok:
        st = r.get("setting", {})
        label = ", ".join(f"{k.split('.')[-1]}={v}" for k, v in list(st.items())[1:]) or "all"
        groups.setdefault(label, []).append(r)
    third = any("packet_steps_mean" in r or "bin_tests_per_ray_mean" in r for r in ok)  # packets or bins swept
    fig, ax = plt.subplots(1, 3 if third else 2, figsize=(14, 4) if third else (9.5, 4))
    for i, (label, rs) in enumerate(groups.items()):
        rs = sorted(rs, key=lambda r: r["primitives"])
        n = np.array([r["primitives"] for r in rs], float)
        ax[0].plot(n, [r["us_per_ray"] for r in rs], "o-", c=f"C{i}", label=label)
        ax[1].plot(n, [r["nodes_per_ray_mean"] for r in rs], "o-", c=f"C{i}", label=f"nodes ({label})")
        ax[1].plot(n, [r["leaves_per_ray_mean"] for r in rs], "s--", c=f"C{i}", label=f"leaves ({label})")
        if any("packet_steps_mean" in r for r in rs):
            ax[2].plot(n, [r.get("packet_steps_mean", np.nan) for r in rs], "o-", c=f"C{i}", label=f"packet steps ({label})")
        if any("bin_tests_per_ray_mean" in r for r in rs):
            ax[2].plot(n, [r.get("bin_tests_per_ray_mean", np.nan) for r in rs], "s--", c=f"C{i}", label=f"bin tests per ray ({label})")
    ax[0].set_ylabel("warm median microseconds per ray")
    ax[1].set_ylabel("per ray, its own walk (mean)")
    if third:
        ax[2].set_ylabel("packets: loop steps; bins: segment tests per ray")
    for a in ax:
        a.set_xscale("log", base=2)
        a.set_xlabel("segments")
        a.set_ylim(bottom=0)
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=7)
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_sweep_file(rows: list[dict], keys: list[str], metric: str, path: Path):
    """Error against warm median time on log axes, the Pareto front marked (:func:`pareto_plot`);
    None when no row has a positive value of ``metric`` (e.g. a sweep without a reference)."""
    pts = [(r, number(r.get("time_median_s")), number(r.get(metric))) for r in rows]
    pts = [(r, t, e) for r, t, e in pts if t is not None and e is not None and e > 0]
    if not pts:
        return None
    mesh = [str(r.get("peer.level", "")) != "" for r, _, _ in pts]
    labels = [f"mesh {r['peer.level']}" if m else ",".join(str(r.get(k, "")) for k in keys) for (r, _, _), m in zip(pts, mesh)]
    title = f"{metric} against time ({rows[0].get('device', '')}); labels: " + ", ".join(k.split(".")[-1] for k in keys)
    return pareto_plot([p[1] for p in pts], [p[2] for p in pts], labels, path, metric, title, mesh, "displaced mesh, Embree")
