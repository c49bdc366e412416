"""Degenerate input rejected where it enters, every problem at once (issue 29, class 4).

A check takes a field path and an array and returns the problems it finds as lines, each
naming the path, the index and the value, in the config errors' form
``<path>[<index>]: <what is wrong> (got <value>)``; where several entries share a problem, one
line gives the count and the first ``SHOW`` (the style of ``jskel.skeletons``' repair report):
``<path>: <n> <noun>: <what is wrong> (indices 3: nan, 7: -1, ...)``. :func:`raise_all` raises
the lines of every check as ONE :class:`jskel.config.ConfigError` (a ``ValueError``; the CLI
prints a line per problem and exits 2).

In a pydantic model, :func:`validate_with` is the body of a ``mode="wrap"`` model validator:
the model's field errors (NaN, inf, out of range: pydantic's own, one per entry) and the
checks between its fields (a tube's two ends coinciding, a segment of zero length) come in one
error, so a NaN in one field does not hide a degenerate pair in another. The config error
formatter places each line under the model's path (``object.tubes[0].b: ...``).

Under jit, :func:`traced` checks traced arrays and :func:`checked` makes the checked variant of a
jitted entry point: every failing check comes back from the program as a :class:`Found` (its
count, first indices and values), so all are raised at once, as the host checks raise them.
"""

from __future__ import annotations

import functools
import re
from dataclasses import dataclass
from typing import Any

import jax
import jax.extend
import jax.numpy as jnp
import numpy as np

from .config import ConfigError, _format

SHOW = 5  # entries named per problem (as jskel.skeletons' repair report)
REL_LENGTH = 1e-9  # two points closer than this fraction of their scale coincide (the frusta build's zero-length bound)


def value_str(v) -> str:
    """A value as the messages print it: ``nan``, ``-1``, ``[0, inf, 2.5]``; strings as given."""
    if isinstance(v, str):
        return v
    a = np.ravel(np.asarray(v, np.float64))
    if a.size == 1:
        return f"{a[0]:.6g}"
    return "[" + ", ".join(f"{x:.6g}" for x in a) + "]"


def at(field: str, what: str, index, values, noun: str = "entries", count: int | None = None) -> list[str]:
    """The problem ``what`` at ``index`` ((k,) ints, or (k, d) for an entry of a d-dimensional
    grid) with ``values`` (one each, or the first SHOW): [] for none, one
    ``field[i]: what (got v)`` line for one, else one line with the count and the first SHOW.
    ``count``: how many entries have it, where ``index`` holds only the first few."""
    index = np.asarray(index, np.int64)
    if index.size == 0:
        return []
    names = [", ".join(str(int(x)) for x in row) for row in index.reshape(index.shape[0] if index.ndim else 1, -1)[:SHOW]]
    n = (index.shape[0] if index.ndim else 1) if count is None else count
    if n == 1:
        return [f"{field}[{names[0]}]: {what} (got {value_str(values[0])})"]
    shown = ", ".join(f"{'(' + i + ')' if ',' in i else i}: {value_str(v)}" for i, v in zip(names, values[:SHOW]))
    return [f"{field}: {n} {noun}: {what} (indices {shown}{', ...' if n > SHOW else ''})"]


def _rows(a) -> np.ndarray:
    """(N, k) float64 view of an (N,) or (N, ...) array-like."""
    a = np.asarray(a, np.float64)
    if a.ndim == 0:
        return a.reshape(1, 1)
    return a.reshape(a.shape[0], int(np.prod(a.shape[1:], dtype=np.int64)))  # (0, k) too: -1 cannot infer k from 0 rows


def nonfinite(field: str, a, noun: str = "entries") -> list[str]:
    """Entries (rows of an (N, ...) array) holding a NaN or an infinity."""
    rows = _rows(a)
    bad = np.nonzero(~np.all(np.isfinite(rows), axis=1))[0]
    return at(field, "not finite", bad, rows[bad], noun)


def zero_vectors(field: str, a, noun: str = "entries") -> list[str]:
    """Rows of an (N, 3) array that are the zero vector (a direction that has none)."""
    rows = _rows(a)
    bad = np.nonzero(np.all(rows == 0, axis=1))[0]
    return at(field, "is the zero vector", bad, rows[bad], noun)


def same_point(field: str, a, b, scale, what: str) -> list[str]:
    """One pair of points (3,) no farther apart than REL_LENGTH x ``scale`` (0: only equal
    points): ``field: what (got b)``; [] otherwise, or where either is not finite."""
    a, b = np.asarray(a, np.float64), np.asarray(b, np.float64)
    length = float(np.linalg.norm(b - a))
    return [f"{field}: {what} (got {value_str(b)})"] if length <= REL_LENGTH * float(scale) else []


def count_mismatch(field: str, got: int, want: int, of: str) -> list[str]:
    """``field: has <got> entries for <want> <of>`` where the counts differ."""
    return [] if got == want else [f"{field}: has {got} entries for {want} {of}"]


def floats(raw, width: int | None = None) -> np.ndarray | None:
    """Unvalidated input (a list from YAML) as a float64 array of rows of ``width``, or None
    where it is not one (pydantic reports why): checks between fields run on what they can."""
    try:
        a = np.asarray(raw, np.float64)
    except (TypeError, ValueError):
        return None
    if raw is None or width is not None and (a.ndim != 2 or a.shape[1] != width):
        return None
    return a


def raise_all(lines: list[str]) -> None:
    """Raise every problem as one ConfigError (one line each); nothing when there is none."""
    if lines:
        raise ConfigError(lines)


def validate_with(data, handler, problems):
    """The body of a pydantic ``mode="wrap"`` model validator: ``handler(data)``'s errors and
    ``problems(data)``'s lines (``data`` the unvalidated mapping, read with :func:`floats`)
    raised together as one ConfigError, each line relative to the model; the model otherwise.
    An instance of the model (already validated) passes through."""
    from pydantic import ValidationError

    if not isinstance(data, dict):
        return handler(data)
    lines = problems(data)
    try:
        model = handler(data)
    except ValidationError as e:
        if not lines:
            raise
        raise ConfigError(_format(e) + lines) from None
    raise_all(lines)
    return model


# ---------------------------------------------------------------------- under jit: checkify

#: what :func:`traced` checks of a field's entries besides being finite, and the word for a failure
KINDS = {"finite": None, "nonnegative": "negative", "positive": "not positive", "nonzero": "is the zero vector"}


@jax.tree_util.register_pytree_node_class
@dataclass(frozen=True)
class Found:
    """What one check of :func:`traced` found, as a compiled program returns it: ``count`` ()
    entries failed it, the first SHOW of them at ``index`` (SHOW,) (the user's index) with
    ``values`` (SHOW, k); the field, the problem's words and the entries' number are static
    (the pytree's aux data), so a program returns them without a host callback."""

    field: str
    what: str
    entries: int
    count: Any
    index: Any
    values: Any

    def tree_flatten(self):
        return (self.count, self.index, self.values), (self.field, self.what, self.entries)

    @classmethod
    def tree_unflatten(cls, aux, children):
        return cls(*aux, *children)

    def lines(self) -> list[str]:
        """Host: the line of :func:`at` with the count of all entries: ``radii[3]: not finite
        (got nan); 1 of 8 entries`` or ``rays.origins: 6 entries: not finite (indices 0: [nan,
        0, 0], ...); 6 of 64 entries``; [] where no entry failed."""
        n = int(self.count)
        k = min(n, SHOW)
        lines = at(self.field, self.what, np.asarray(self.index)[:k], np.asarray(self.values)[:k], count=n)
        return [f"{line}; {n} of {self.entries} entries" for line in lines]


def traced(field: str, a, kind: str = "finite", valid=None, ids=None) -> list[Found]:
    """Inside a function under ``jax.experimental.checkify.checkify``: check that every entry
    (row of an (N, ...) array) of traced ``a`` is finite, and for ``kind`` ``nonnegative``,
    ``positive`` or ``nonzero`` at least 0, above 0 or not the zero vector, where ``valid`` (N,)
    (padding rows skipped). Returns a :class:`Found` per check (every failing entry counted,
    the first SHOW named by ``ids[i]`` where given: the user's index of a packed row), which
    :func:`checked` turns into one line each; the ``checkify`` check each also makes names the
    first bad entry, for a caller that checkifies its own function. Only checked programs
    call this, so unchecked programs hold none of it."""
    from jax.experimental import checkify

    rows = jnp.reshape(a, (a.shape[0] if a.ndim else 1, -1))
    n, k = rows.shape
    live = jnp.ones((n,), bool) if valid is None else jnp.asarray(valid, bool)
    good = {"finite": None, "nonnegative": lambda: rows >= 0, "positive": lambda: rows > 0, "nonzero": lambda: jnp.any(rows != 0, axis=1, keepdims=True)}
    finite = jnp.all(jnp.isfinite(rows), axis=1)
    tests = [("not finite", finite)]
    if KINDS[kind] is not None:  # of the finite entries (a NaN is named once, as not finite)
        tests.append((KINDS[kind], jnp.all(good[kind](), axis=1) | ~finite))
    found = []
    for what, ok in tests:
        bad = live & ~ok
        count = jnp.sum(bad).astype(jnp.int32)
        (pos,) = jnp.nonzero(bad, size=SHOW, fill_value=0)
        index = pos if ids is None else jnp.asarray(ids)[pos]
        checkify.check(count == 0, f"{field}[{{i}}]: {what}; {{count}} of {n} entries", i=index[0], count=count)
        found.append(Found(field, what, n, count, index, rows[pos]))
    return found


def checked(fn, problems, static_argnums=()):
    """``fn`` with its traced inputs checked inside one compiled program: ``problems(*args)``
    returns the :class:`Found` of :func:`traced` calls on the arguments, and the checked
    function raises every failing check as one line of one :class:`ConfigError` (a
    ``ValueError``), e.g. ``rays.origins[5]: not finite (got [0, nan, 1]); 1 of 64 entries``,
    instead of returning silent misses. ``checkify`` reports only a program's first failing
    check; the counts and first indices travel as outputs instead, so every field's problem
    is named at once. The program (``.program``, one ``jax.jit``) is cached by JAX as ``fn``
    would be: new values of the same shapes compile nothing. Once a check fails, ``fn``'s work is
    skipped (a ``lax.cond``; the call raises instead of returning). Only the checks are checkified:
    ``checkify`` does not enter a vmap of a while loop, which every marching tracer is."""
    from jax.experimental import checkify

    def both(*args):
        err, found = checkify.checkify(problems)(*args)
        # a value found bad skips the work it would spoil (a zero march step runs every ray to
        # its step cap): ``lax.cond`` on one scalar is a real branch, and the zeros it returns
        # instead are never seen, because ``run`` raises
        # (``fn`` traced once, to a jaxpr the branch evaluates: its zeros need its shapes)
        bad = functools.reduce(jnp.logical_or, [f.count > 0 for f in found], jnp.bool_(False))
        closed, shapes = jax.make_jaxpr(lambda: fn(*args), return_shape=True)()
        leaves, tree = jax.tree_util.tree_flatten(shapes)
        out = jax.lax.cond(bad, lambda: [jnp.zeros(s.shape, s.dtype) for s in leaves], jax.extend.core.jaxpr_as_fun(closed))
        return err, found, tree.unflatten(out)

    program = jax.jit(both, static_argnums=static_argnums)

    def run(*args):
        err, found, out = program(*args)
        lines = [line for f in jax.device_get(found) for line in f.lines()]  # (one transfer for all)
        raise_all(lines or ([re.sub(r" \((`check` failed|check failed at).*$", "", err.get().splitlines()[0])] if err.get() else []))
        return out

    run.program = program
    run.__doc__ = f"``{fn.__name__}`` checked under jit (``jskel.checks.checked``)."
    return run
