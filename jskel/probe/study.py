"""What every peer study is given and how its depths are scored against jskel's reference.

A study is ``fn(exp, ref_hits, runs, rows, options) -> [row]``: the experiment of the bench's
reference job (a study of one object takes its shape by :func:`shape_of`), the reference render's hits, the number of warm runs, jskel's rows
of the same group (for ratios and "similar quality" targets) and :class:`StudyOptions`.
"""

from __future__ import annotations

from typing import Any, Callable, Mapping, NamedTuple

from .metrics import compare


class StudyOptions(NamedTuple):
    """The bench file's peer keys: subdivision or grid ``levels``, the jskel setting whose error a
    peer must match (``match``: key -> value, or None), animated ``frames`` and the Mitsuba
    variant to try first."""

    levels: tuple = (0, 1, 2, 3, 4, 5)
    match: dict | None = None
    frames: tuple = ()
    mitsuba_variant: str = "llvm_ad_rgb"


class Peers(NamedTuple):
    """The peers a harness command may run, handed to it by its caller (the CLI passes
    ``jskel.peers.PEERS``), so that ``jskel.measure`` and ``jskel.peers`` import neither the
    other: ``studies`` by the name a bench file's ``peer:`` gives them, each a study as above;
    ``mesh``: a sweep's ``peer: embree_mesh`` (a study too); ``mitsuba_image``: the latency
    benchmark's Mitsuba process, ``(exp, folder, variant) -> (command or None, image path
    or why not)``; ``fit_real``: a bench file with a ``fit_real:`` section, fits of real meshes
    beside a skeletonizer (``peers.skeletonizer``). An empty default: a file that asks for a
    peer not given is refused."""

    studies: Mapping[str, Callable] = {}
    mesh: Callable | None = None
    mitsuba_image: Callable | None = None
    fit_real: tuple | None = None  # (the file's model, its runner (section, emit) -> rows): a ``fit_real:`` bench


def shape_of(exp, key: str):
    """The one object's shape of ``exp``, what a study of one object takes (its cast alone, a
    peer's mesh or curves of it, in the object's own frame); a ValueError naming the file's
    ``key`` where the experiment is a scene of several objects or moves its object."""
    if len(exp.objects) != 1 or exp.objects[0].is_placed:
        what = f"{len(exp.objects)} objects" if len(exp.objects) != 1 else "an object moved by a transform or motion"
        raise ValueError(f"{key}: studies one object in its own frame (got {what})")
    return exp.objects[0].shape


def needed(what, key: str, value) -> Any:
    """``what``, or a ValueError naming the file's ``key`` and ``value`` where the caller gave
    no such peer (:class:`Peers`)."""
    if what is None:
        raise ValueError(f"{key}: {value!r} asks for a peer that was not given (the CLI passes jskel.peers.PEERS)")
    return what


class Depths(NamedTuple):
    """A peer's depths as ``metrics.compare`` reads hits (no normals: depth metrics only)."""

    t: Any
    normal: Any = None


def match_target(match: dict | None, rows: list[dict]) -> dict | None:
    """The last of jskel's ``rows`` whose setting has every key of ``match`` (None without one)."""
    if match is None:
        return None
    target = None
    for r in rows:
        if all(r.get("setting", {}).get(k) == v for k, v in match.items()):
            target = r
    return target


def scored(row: dict, t, ref_hits, target: dict | None) -> dict:
    """``row`` with the error metrics of a peer's depths ``t`` against the reference and, given
    jskel's ``target`` row, whether the peer is at most as wrong in depth and hit/miss."""
    row.update({k: (round(v, 8) if isinstance(v, float) else v) for k, v in compare(Depths(t), ref_hits).items()})
    if target is not None:
        row["matches_jskel_setting"] = bool(row["depth_rmse"] is not None and row["depth_rmse"] <= target["depth_rmse"]
                                            and row["hit_miss_pct"] <= target["hit_miss_pct"])
        row["jskel_setting"] = target["setting"]
    return row
