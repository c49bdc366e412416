"""Peers used only in benchmarks (install with ``pip install -e ".[peers]"``; tests never need
the extra): Embree (through trimesh and embreex), Mitsuba 3, marching cubes (scikit-image)
and skeletor's skeletonization (with navis' example meshes: ``skeletonizer``),
each imported only when a peer runs. Their studies, which the bench runs by name
(``peers.studies.STUDIES``), live here too: ``mesh_studies``, ``skeleton_study`` and
``frames_study``."""
