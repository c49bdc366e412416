"""Render README's gallery: every listed experiment through ``python -m jskel render`` (the
command a user runs), at 320x240, copied to ``docs/gallery/<name>.png``, with
``docs/gallery/gallery.md`` (the whole table, linked from the repository root; README.md shows
eight of its images, docs/index.md all of them). Each run's seconds are printed, not written
into the table: a render time belongs in a result file with its provenance, and
``experiments/bench_latency.yaml`` times these same experiments (``docs/bench_latency_cpu.jsonl``).

    python docs/gallery.py            # from the repository root
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / "docs" / "gallery"
EXPERIMENTS = [  # (experiment, caption)
    ("saguaro", "frusta: saguaro, 30 segments"),
    ("aloe", "frusta: aloe, 229 segments"),
    ("palm", "frusta: coconut palm, 3,713 segments (BVH)"),
    ("relief_column", "relief: brick height field in a shell"),
    ("gecko", "implicit: gecko, 66 metaballs"),
    ("spider", "implicit: spider, metatube bones"),
    ("torus_cells", "cells: Voronoi torus, first hit"),
    ("torus_cells_refraction", "cells: refraction"),
    ("neuron_swc", "frusta: a published neuron from SWC, framed automatically"),
    ("scene_effects", "scene: shadows, mirror, glass"),
    ("scene_cacti", "scene: dancing cacti, sun and mirror ball"),
]


def main() -> int:
    OUT.mkdir(parents=True, exist_ok=True)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for name, caption in EXPERIMENTS:
            out = Path(tmp) / name
            cmd = [sys.executable, "-m", "jskel", "render", str(ROOT / "experiments" / f"{name}.yaml"), "--out", str(out),
                   "--set", "camera.width=320", "--set", "camera.height=240", "--no-progress"]
            subprocess.run(cmd, check=True, cwd=ROOT)
            shutil.copy(out / "image.png", OUT / f"{name}.png")
            run = json.loads((out / "run.json").read_text())
            rows.append((name, caption))
            print(f"{name}: {run['render_s']:.2f} s (compile {run['compile_s']:.1f} s)")
    lines = ["| | | | |", "| --- | --- | --- | --- |"]
    for i in range(0, len(rows), 4):
        group = rows[i:i + 4]
        pad = [""] * (4 - len(group))
        lines.append("| " + " | ".join([f"![{n}](docs/gallery/{n}.png)" for n, _ in group] + pad) + " |")
        lines.append("| " + " | ".join([c for _, c in group] + pad) + " |")
    (OUT / "gallery.md").write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
