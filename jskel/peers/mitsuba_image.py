"""Mitsuba 3's time to first image of a skeleton, the reference row of the latency benchmark
(``jskel.measure.latency``): a fresh process that imports Mitsuba, loads the skeleton's
segments as a ``linearcurve`` scene with the experiment's camera, renders one sample per pixel
and writes a PNG.

:func:`prepare` (in the bench's process) writes the curve file and a JSON spec; the timed
process runs this file by path (``python mitsuba_image.py SPEC``), so it imports neither jskel
nor JAX: its time is Mitsuba's own.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def prepare(exp, folder: Path, variant: str = "scalar_rgb") -> tuple[list[str] | None, str]:
    """Write ``folder``/curves.txt and spec.json for the one skeleton object of ``exp``.
    Returns (the command to time, the PNG it writes), or (None, why) when it cannot run."""
    import importlib.util

    if importlib.util.find_spec("mitsuba") is None:
        return None, "mitsuba is not installed (pip install -e '.[peers]')"
    from .. import registry
    from .skeleton import curve_points

    obj = exp.objects[0].shape
    sk = registry.get(obj.type).skeleton(obj) if len(exp.objects) == 1 and not exp.objects[0].is_placed else None
    if sk is None:
        return None, "not a single skeleton object"
    if exp.camera.frame == "auto":
        return None, "camera.frame is auto (the peer needs the camera placed by hand)"
    j, r, p = sk
    folder.mkdir(parents=True, exist_ok=True)
    pts = curve_points(j, r, p)
    (folder / "curves.txt").write_text("\n\n".join("\n".join(" ".join(f"{x:.9g}" for x in q) for q in c) for c in pts) + "\n")
    c = exp.camera
    png = folder / "image.png"
    spec = {"variant": variant, "curves": str(folder / "curves.txt"), "png": str(png), "eye": list(c.eye), "target": list(c.target),
            "up": list(c.up), "fov_deg": c.fov_deg, "width": c.width, "height": c.height}
    (folder / "spec.json").write_text(json.dumps(spec))
    return [sys.executable, str(Path(__file__).resolve()), str(folder / "spec.json")], str(png)


def _render(spec: dict) -> None:
    import mitsuba as mi

    mi.set_variant(spec["variant"])
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": spec["fov_deg"], "fov_axis": "y",
                   "to_world": mi.ScalarTransform4f().look_at(origin=spec["eye"], target=spec["target"], up=spec["up"]),
                   "film": {"type": "hdrfilm", "width": spec["width"], "height": spec["height"], "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "sun": {"type": "directional", "direction": [-0.5, -0.8, -0.6]},
        "sky": {"type": "constant", "radiance": 0.2},
        "curves": {"type": "linearcurve", "filename": spec["curves"]},
    })
    mi.util.write_bitmap(spec["png"], mi.render(scene))


if __name__ == "__main__":
    _render(json.loads(Path(sys.argv[1]).read_text()))
