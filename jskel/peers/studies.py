"""The peers' studies by the name a bench file gives them (``peer:``), each
``fn(exp, obj, ref_hits, runs, rows, options) -> [row]`` (``peers.study``)."""

from __future__ import annotations

from . import mesh_studies
from .skeleton_study import skeleton
from .study import StudyOptions as StudyOptions

STUDIES = {
    "embree_mesh": mesh_studies.embree_mesh,
    "embree_same_mesh": mesh_studies.embree_same_mesh,
    "marching_cubes": mesh_studies.marching_cubes,
    "skeleton": skeleton,
}

__all__ = ["STUDIES", "StudyOptions"]
