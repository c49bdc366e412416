"""Progress bars for long host work (``jskel.progress``): shown on a terminal, hidden in CI and
when standard error is not a terminal; the cell membership precompute reports every active tile."""

from __future__ import annotations

import sys

import numpy as np

from jskel import progress
from jskel.cells._membership import membership
from jskel.cells._tiles import part_links, part_offsets, split_cells, sphere_tile


class _Tty:
    def isatty(self):
        return True

    def write(self, s):
        return len(s)

    def flush(self):
        pass


def test_bars_show_on_a_terminal_and_hide_in_ci(monkeypatch):
    monkeypatch.setattr(sys, "stderr", _Tty())
    monkeypatch.delenv("CI", raising=False)
    assert not progress.quiet() and not progress.bar(3, "x", "it").disable
    monkeypatch.setenv("CI", "true")
    assert progress.quiet() and progress.bar(3, "x", "it").disable


def test_membership_reports_its_tiles_as_it_measures_them():
    """A ball of radius 0.3 tiled 4^3 times over [-1, 1]^3: every tile the sphere's surface
    crosses must be measured voxel by voxel, so the progress callbacks add up to at least their
    number (counted here in NumPy: a tile is crossed where its nearest point is inside the ball
    and its farthest is not) and at most every tile."""
    tile = sphere_tile(8, 4, 0.3)
    sc = split_cells(tile)
    offsets = part_offsets(sc, part_links(sc), "t")
    done = []
    n, lo, size = 4, np.array([-1.0, -1.0, -1.0]), 0.5
    membership(sc, offsets, lambda p: np.linalg.norm(p, axis=-1) < 0.3, lo, size, n, progress=done.append)
    c = lo + size * np.stack(np.meshgrid(*[np.arange(n)] * 3, indexing="ij"), -1)  # tile corners
    near = np.linalg.norm(np.clip(0.0, c, c + size), axis=-1)
    far = np.linalg.norm(np.maximum(np.abs(c), np.abs(c + size)), axis=-1)
    crossed = int(np.sum((near < 0.3) & (far >= 0.3)))
    assert crossed > 0 and sum(done) >= crossed and sum(done) <= n ** 3


def test_bars_show_in_a_notebook_whose_stream_is_not_a_terminal(monkeypatch):
    """ipykernel's standard error says it is no terminal; a kernel still shows ``tqdm.auto``'s
    widgets, so the bars are on there (outside CI), and off in a plain IPython shell."""
    import types

    class _Pipe(_Tty):
        def isatty(self):
            return False

    monkeypatch.setattr(sys, "stderr", _Pipe())
    monkeypatch.delenv("CI", raising=False)
    shell = types.SimpleNamespace()
    monkeypatch.setitem(sys.modules, "IPython", types.SimpleNamespace(get_ipython=lambda: shell))
    assert progress.quiet() and not progress.in_notebook()  # a terminal-less shell without a kernel
    shell.kernel = object()
    assert progress.in_notebook() and not progress.quiet()
    monkeypatch.setenv("CI", "true")
    assert progress.quiet()


def test_a_long_build_says_what_it_builds_and_a_short_one_nothing(monkeypatch, capsys):
    """``progress.notice_after``: its line once the work has taken the delay (a timer thread),
    nothing for work that ends sooner or where bars are quiet; every object a scene builds, and
    a single object, is built inside one, with ``BUILD_NOTICE_S``."""
    import time

    from jskel import config
    from jskel.render import _build

    monkeypatch.setattr(progress, "quiet", lambda: False)
    with progress.notice_after(0.05, "building x"):
        time.sleep(0.4)
    with progress.notice_after(5.0, "building y"):
        pass
    monkeypatch.setattr(progress, "quiet", lambda: True)
    with progress.notice_after(0.0, "building z"):
        time.sleep(0.2)
    assert capsys.readouterr().err == "jskel: building x ...\n"
    said = []

    @__import__("contextlib").contextmanager
    def notice(delay, message):
        said.append((delay, message))
        yield

    monkeypatch.setattr(progress, "notice_after", notice)
    seg = {"type": "frusta", "skeleton": {"joints": [[0, 0, 0], [0, 1, 0]], "radii": [0.2, 0.2], "parents": [-1, 0]}}
    exp = config.validate({"objects": [{"name": "a", "shape": seg}, {"shape": seg}]})
    _build.place_objects(exp, np.float32)
    exp1 = config.validate({"object": seg})
    _build.place_objects(exp1, np.float32)
    d = _build.BUILD_NOTICE_S
    assert said == [(d, "building a (frusta, 1 of 2)"), (d, "building objects[1] (frusta, 2 of 2)"), (d, "building the object (frusta)")]
    assert 0.5 <= d <= 2.0
