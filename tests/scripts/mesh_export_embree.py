"""The frusta exported as a mesh (``jskel.frusta.export_mesh``) cast by Embree (the ``[peers]``
extra: embreex through trimesh) on the rays of ``tests/test_skeleton_export.py``: Embree's hits
must match jskel's analytic frusta within the facets' sagitta, by the same check the suite runs
on jskel's own mesh representation (``check_mesh_hits``). Tests never need the peers, so this
runs by hand and prints one JSON line:

    python tests/scripts/mesh_export_embree.py
"""

import json
import sys
import tempfile
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))  # tests/: conftest and the test module

from test_skeleton_export import LEVEL, _cfg, check_mesh_hits, frusta_t, view_rays  # noqa: E402

from jskel import frusta, mesh  # noqa: E402
from jskel.peers.skeleton import EmbreeMesh  # noqa: E402

with tempfile.TemporaryDirectory() as tmp:
    path = Path(tmp) / "frusta.ply"
    frusta.export_mesh(path, _cfg(), LEVEL)
    v, f, _ = mesh.read_mesh(str(path))
    O, D = view_rays(64, 48)
    te, _ = EmbreeMesh(np.asarray(v, np.float64), np.asarray(f, np.int64)).cast(O, D)
    # Embree intersects in float32: t of ~4 rounds to ~5e-7, its watertight test a few ulps more
    print(json.dumps({"peer": "embree", "level": LEVEL, **check_mesh_hits(frusta_t(O, D), te, O, D, path, t_tol=2e-5)}))
