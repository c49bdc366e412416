"""Write the meshes the mesh experiments read (trimesh's generators; nothing is committed):

    python experiments/meshes/make.py        # -> out/meshes/*.ply
"""

from pathlib import Path

import trimesh

out = Path("out/meshes")
out.mkdir(parents=True, exist_ok=True)
trimesh.creation.icosphere(subdivisions=6, radius=1.0).export(out / "icosphere6.ply")  # 81,920 triangles
trimesh.creation.torus(major_radius=1.0, minor_radius=0.35, major_sections=256, minor_sections=96).export(out / "torus.ply")  # 49,152
print(sorted(str(p) for p in out.glob("*.ply")))
