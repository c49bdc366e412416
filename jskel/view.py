"""Interactive exploration in Jupyter: ``jskel.view(experiment)`` shows the render with
ipywidgets controls (the ``[notebook]`` extra installs them)::

    import jskel
    v = jskel.view("experiments/saguaro.yaml", width=320, height=240)
    v                        # the image, orbit, zoom, AOV, quality knobs, traced parameters

What a control changes:

* orbit (azimuth about the camera's up axis, elevation towards it, both around the target) and
  zoom (the eye's distance to the target divided by it): the camera pose, a traced value;
* the object's traced parameters (:func:`default_controls`: a scale of every radius, an offset
  of the last joint, the implicit threshold): new values of the same shapes;
* the AOV shown (:data:`AOVS`, the panels of ``jskel render --aov-sheet``): nothing is traced
  again, the last render's outputs are drawn;
* a representation's quality knobs (:func:`default_knobs`: march steps, bisection steps, step
  lengths). Step counts are static options: each new count compiles once (then JAX keeps it),
  step lengths are traced.

So orbit, zoom, the AOV and the traced parameters re-render with the programs already compiled
(the executor pads ray counts to buckets and the render reuses compiled programs when only
values change: docs/rendering.md, "Programs shared across sizes"); the status line says how many
programs each re-render handed to XLA (``jskel.compile.cache.program_counts``).

The state -> image part is pure and has no widget in it (:class:`State`, :func:`apply`,
:func:`frame`), so tests drive :class:`View`'s callbacks headless and compare its image with a
direct :func:`jskel.render.render` of the changed experiment (``tests/test_view.py``).
"""

from __future__ import annotations

import base64
import copy
import io
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, NamedTuple

import numpy as np

from .compile.cache import count_programs, program_counts
from .config import read_yaml, resolved, set_path, validate

AOVS = ("image", "depth", "normals", "uv", "ids", "flags")
"""The AOVs a view shows, drawn as ``jskel render --aov-sheet`` draws them (render/_sheet.py)."""

QUALITY_KEYS = ("steps", "bisection", "steps_per_tile", "step", "eps")
"""Keys of an object section (or of a section inside it, e.g. ``relief``) offered as quality knobs."""

MAX_ELEVATION = 85.0  # degrees: the orbit stops short of the up axis, where the camera's frame is undefined


class Control(NamedTuple):
    """One slider on a config key. ``path``: the dotted key, list indices allowed
    (``object.skeleton.joints.4.0``); ``mode``: ``set`` (the slider's value is the key's),
    ``scale`` (the file's value, or each number of a list, times the slider's) or ``add`` (plus
    it); ``lo``, ``hi``, ``value``: the slider's range and start; ``integer``: an integer slider."""

    path: str
    mode: Literal["set", "scale", "add"]
    lo: float
    hi: float
    value: float
    integer: bool = False


@dataclass(frozen=True)
class State:
    """What a view shows: the orbit (degrees from the experiment's camera), the zoom, the AOV
    and each control's slider value by its label."""

    azimuth: float = 0.0
    elevation: float = 0.0
    zoom: float = 1.0
    aov: str = "image"
    values: dict = field(default_factory=dict)


def base_of(experiment, width: int | None = None, height: int | None = None) -> dict:
    """An experiment as the plain dict a view changes, holding only the keys it sets (a key
    written out at its default can mean something else: a single object's light casts shadows
    only where its section says so): ``experiment`` is a file path, a raw dict or the
    ``Experiment`` ``jskel.config.load`` returns (a file's ``object:`` written back as one);
    ``width`` and ``height`` override the camera's.
    Validated here, so a bad experiment is one ``ConfigError`` naming every problem."""
    if isinstance(experiment, (str, Path)):
        raw = read_yaml(experiment)
    elif isinstance(experiment, dict):
        raw = copy.deepcopy(experiment)
    else:
        exp = experiment
        raw = exp.model_dump(mode="json", exclude_unset=True)
        if len(exp.objects) == 1 and exp.objects[0].at(0) == "object":  # as its file wrote it
            raw["object"] = exp.objects[0].shape.model_dump(mode="json", exclude_unset=True)
            del raw["objects"]
    for key, v in (("width", width), ("height", height)):
        if v is not None:
            raw.setdefault("camera", {})[key] = int(v)
    validate(raw)
    return raw


def full_of(base: dict) -> dict:
    """``base`` with every key at its value (``jskel.config.resolved``): where a control reads
    a value that ``base`` leaves at its default."""
    full = resolved(validate(base))
    if "object" in base:  # keyed as ``base`` is: a file's object section, not the scene of one it loads as
        full["object"] = full.pop("objects")[0]["shape"]
    return full


def _rotate(v: np.ndarray, axis: np.ndarray, deg: float) -> np.ndarray:
    """``v`` rotated by ``deg`` degrees about the unit ``axis`` (Rodrigues, right-handed)."""
    c, s = np.cos(np.deg2rad(deg)), np.sin(np.deg2rad(deg))
    return v * c + np.cross(axis, v) * s + axis * np.dot(axis, v) * (1.0 - c)


def orbit(camera: dict, azimuth: float, elevation: float, zoom: float) -> list[float]:
    """The eye of ``camera`` (a camera section with ``eye``, ``target``, ``up``) turned by
    ``azimuth`` degrees about the up axis through the target, then raised by ``elevation``
    degrees towards up (the total elevation kept within +-85 degrees), its distance to the target
    divided by ``zoom`` (float64, host)."""
    eye, target = np.asarray(camera["eye"], np.float64), np.asarray(camera["target"], np.float64)
    up = np.asarray(camera["up"], np.float64)
    up = up / np.linalg.norm(up)
    v = _rotate(eye - target, up, azimuth)
    now = np.rad2deg(np.arcsin(np.clip(np.dot(v, up) / np.linalg.norm(v), -1.0, 1.0)))
    want = np.clip(now + elevation, -MAX_ELEVATION, MAX_ELEVATION)
    side = np.cross(v, up)
    if np.linalg.norm(side) > 0 and want != now:
        v = _rotate(v, side / np.linalg.norm(side), want - now)
    return [float(x) for x in target + v / zoom]


def _parts(path: str) -> list:
    return [int(p) if p.lstrip("-").isdigit() else p for p in path.split(".")]


def get_path(raw: dict, path: str):
    """The value at a dotted ``path`` of ``raw`` (list indices allowed); KeyError or IndexError if absent."""
    cur = raw
    for p in _parts(path):
        cur = cur[p]
    return cur


def _changed(value, mode: str, x: float):
    if isinstance(value, list):
        return [_changed(v, mode, x) for v in value]
    return value * x if mode == "scale" else value + x


def apply(base: dict, state: State, controls: dict[str, Control], full: dict | None = None) -> dict:
    """The experiment ``base`` (:func:`base_of`) as ``state`` shows it: the camera orbited and
    zoomed (:func:`orbit`), each control's key changed by its slider value (a control without a
    value in ``state`` keeps its start). Values ``base`` leaves at their defaults are read from
    ``full`` (default :func:`full_of`). Pure: ``base`` is not changed."""
    full = full_of(base) if full is None else full
    raw = copy.deepcopy(base)
    cam = full["camera"]
    raw.setdefault("camera", {})
    raw["camera"].update(eye=orbit(cam, state.azimuth, state.elevation, state.zoom), target=list(cam["target"]), frame="manual")
    for label, c in controls.items():
        x = state.values.get(label, c.value)
        x = int(round(x)) if c.integer else float(x)
        new = x
        if c.mode != "set":
            try:
                new = _changed(copy.deepcopy(get_path(raw, c.path)), c.mode, x)
            except (KeyError, IndexError):
                new = _changed(copy.deepcopy(get_path(full, c.path)), c.mode, x)
        set_path(raw, c.path, new)
    return raw


def aov_image(res, aov: str, width: int, height: int) -> np.ndarray:
    """The (H, W, 3) uint8 picture of one AOV of a render result (:data:`AOVS`)."""
    from .render import panels_of

    if aov not in AOVS:
        raise ValueError(f"aov: {aov!r} is not one of {', '.join(AOVS)}")
    if aov == "image":
        return np.asarray(res.image)
    h = res.hits
    shape = (height, width)
    flags = None if h.flags is None else np.asarray(h.flags).reshape(shape)
    p = panels_of(res.image, np.asarray(h.t).reshape(shape), np.asarray(h.normal).reshape(shape + (3,)),
                  np.asarray(h.uv).reshape(shape + (2,)), np.asarray(h.prim).reshape(shape), flags)
    return p[aov]


def frame(raw: dict, aov: str = "image"):
    """Render the experiment ``raw`` (a plain dict) and draw ``aov``: (image (H, W, 3) uint8,
    the render's result, programs handed to XLA by the render: compiled + loaded)."""
    from .render import render

    exp = validate(raw)
    count_programs()
    before = program_counts()
    res = render(exp, progress=False)
    after = program_counts()
    programs = after["compiled"] - before["compiled"] + after["loaded"] - before["loaded"]
    return aov_image(res, aov, exp.camera.width, exp.camera.height), res, programs


def default_controls(base: dict) -> dict[str, Control]:
    """The traced parameters a view offers for ``base``'s object: a scale of every radius and an
    offset (x, y) of the last joint of a skeleton given by joints and radii, a scale of a skeleton
    read from a file or made procedurally, an object's ``scale`` and an implicit ``threshold``."""
    obj = base.get("object") or {}
    sk = obj.get("skeleton") if isinstance(obj.get("skeleton"), dict) else None
    out = {}
    if sk is not None and isinstance(sk.get("radii"), list) and isinstance(sk.get("joints"), list):
        out["radius scale"] = Control("object.skeleton.radii", "scale", 0.5, 2.0, 1.0)
        j = np.asarray(sk["joints"], np.float64)
        reach = 0.25 * float(np.max(np.ptp(j, axis=0))) if len(j) > 1 else 0.5
        for axis, name in ((0, "x"), (1, "y")):
            out[f"last joint {name}"] = Control(f"object.skeleton.joints.{len(j) - 1}.{axis}", "add", -reach, reach, 0.0)
    elif sk is not None and "scale" in sk:
        out["skeleton scale"] = Control("object.skeleton.scale", "scale", 0.5, 2.0, 1.0)
    elif isinstance(obj.get("scale"), (int, float)):
        out["scale"] = Control("object.scale", "scale", 0.5, 2.0, 1.0)
    if isinstance(obj.get("threshold"), (int, float)):
        t = float(obj["threshold"])
        out["threshold"] = Control("object.threshold", "set", 0.5 * t, 1.5 * t, t)
    return out


def default_knobs(base: dict) -> dict[str, Control]:
    """The quality knobs a view offers for ``base``'s object: each key of :data:`QUALITY_KEYS` in
    the object section or a section inside it, as a slider on its value (integers from 1, or 0 for
    bisection, to four times the value; lengths from a tenth to ten times)."""
    obj = base.get("object") or {}
    out = {}
    sections = [("object", obj)] + [(f"object.{k}", v) for k, v in obj.items() if isinstance(v, dict)]
    for where, sec in sections:
        for key in QUALITY_KEYS:
            v = sec.get(key)
            if isinstance(v, bool) or not isinstance(v, (int, float)):
                continue
            label = f"{where}.{key}"[len("object."):]
            if isinstance(v, int):
                out[label] = Control(f"{where}.{key}", "set", 0 if key == "bisection" else 1, max(4 * v, 8), v, integer=True)
            else:
                out[label] = Control(f"{where}.{key}", "set", v / 10, v * 10, v)
    return out


def png_bytes(image: np.ndarray) -> bytes:
    """``image`` (H, W, 3) uint8 as PNG file bytes."""
    import imageio.v3 as iio

    buf = io.BytesIO()
    iio.imwrite(buf, np.asarray(image, np.uint8), extension=".png")
    return buf.getvalue()


def _slider(widgets, label: str, c: Control):
    cls = widgets.IntSlider if c.integer else widgets.FloatSlider
    step = 1 if c.integer else (c.hi - c.lo) / 100
    return cls(value=c.value, min=c.lo, max=c.hi, step=step, description=label, continuous_update=False,
               style={"description_width": "initial"})


class View:
    """The widget :func:`view` returns: the image of the current :class:`State` and its
    controls. ``sliders`` holds every control's widget by label (``azimuth``, ``elevation``,
    ``zoom``, ``aov``, then the quality knobs and the traced parameters); setting a widget's
    ``value`` re-renders (:meth:`update`), as moving it does. ``image`` is the (H, W, 3) uint8
    picture shown, ``result`` the last render's result, ``programs`` what its render handed to XLA."""

    def __init__(self, experiment, controls: dict[str, Control] | None = None, knobs: dict[str, Control] | None = None,
                 width: int | None = None, height: int | None = None):
        import ipywidgets as widgets

        base = base_of(experiment, width, height)
        self.image, self.result, self.programs = frame(base)
        # the first render resolves camera.frame: auto; its eye and target are the orbit's start
        cam = self.result.run["config"]["camera"]
        base.setdefault("camera", {}).update(eye=list(cam["eye"]), target=list(cam["target"]), frame="manual")
        self.base, self.full = base, full_of(base)
        self.controls = {**(default_knobs(self.full) if knobs is None else knobs),
                         **(default_controls(self.full) if controls is None else controls)}
        kw = {"continuous_update": False, "style": {"description_width": "initial"}}
        self.sliders = {
            "azimuth": widgets.FloatSlider(value=0.0, min=-180.0, max=180.0, step=5.0, description="azimuth", **kw),
            "elevation": widgets.FloatSlider(value=0.0, min=-80.0, max=80.0, step=5.0, description="elevation", **kw),
            "zoom": widgets.FloatLogSlider(value=1.0, base=2.0, min=-2.0, max=2.0, step=0.125, description="zoom", **kw),
            "aov": widgets.Dropdown(options=list(AOVS), value="image", description="AOV"),
            **{label: _slider(widgets, label, c) for label, c in self.controls.items()},
        }
        self._picture = widgets.Image(value=png_bytes(self.image), format="png")
        self._status = widgets.HTML()
        self._say()
        for w in self.sliders.values():
            w.observe(self._on_change, names="value")
        self.widget = widgets.HBox([self._picture, widgets.VBox(list(self.sliders.values()) + [self._status])])

    @property
    def state(self) -> State:
        """The :class:`State` the widgets show now."""
        s = self.sliders
        values = {label: s[label].value for label in self.controls}
        return State(s["azimuth"].value, s["elevation"].value, s["zoom"].value, s["aov"].value, values)

    def experiment(self) -> dict:
        """The experiment (a plain dict) the current state renders."""
        return apply(self.base, self.state, self.controls, self.full)

    def _on_change(self, change) -> None:
        if change["owner"] is self.sliders["aov"]:
            self.show()
        else:
            self.update()

    def update(self) -> None:
        """Render the current state and show it (a bad value is shown in the status line; the
        image stays as it was)."""
        from .config import ConfigError

        try:
            self.image, self.result, self.programs = frame(self.experiment(), self.state.aov)
        except (ConfigError, ValueError) as e:
            self._status.value = f"<pre>{e}</pre>"
            return
        self._picture.value = png_bytes(self.image)
        self._say()

    def show(self) -> None:
        """Draw the last render's outputs as the AOV chosen (no render)."""
        cam = self.result.run["config"]["camera"]
        self.image = aov_image(self.result, self.state.aov, cam["width"], cam["height"])
        self._picture.value = png_bytes(self.image)

    def _say(self) -> None:
        run = self.result.run
        self._status.value = (f"render {1e3 * run['render_s']:.1f} ms, compile {run['compile_s']:.2f} s, "
                              f"programs handed to XLA: {self.programs}")

    def _repr_mimebundle_(self, **kwargs):
        """The widget in a live notebook, and the current image as a PNG where widgets are not
        drawn (a notebook's stored outputs, the documentation's pages)."""
        bundle = self.widget._repr_mimebundle_(**kwargs) or {}
        return {**bundle, "image/png": base64.b64encode(png_bytes(self.image)).decode("ascii"), "text/plain": repr(self)}

    def __repr__(self) -> str:
        h, w = self.image.shape[:2]
        return f"<jskel view of {self.base.get('name', 'experiment')!r}: {w}x{h}, AOV {self.state.aov}>"


def view(experiment, controls: dict[str, Control] | None = None, knobs: dict[str, Control] | None = None,
         width: int | None = None, height: int | None = None) -> View:
    """Show ``experiment`` (a file path, a raw dict or ``(experiment, object)``) with controls
    in a notebook: orbit, zoom, the AOV, ``knobs`` (default :func:`default_knobs`) and
    ``controls`` (the traced parameters, default :func:`default_controls`), each a label ->
    :class:`Control`; ``width`` and ``height`` override the camera's. Needs ipywidgets
    (``pip install -e ".[notebook]"``)."""
    return View(experiment, controls, knobs, width, height)
