"""The peers' studies by the name a bench file gives them (``peer:``), each
``fn(exp, ref_hits, runs, rows, options) -> [row]`` (``probe.study``), and :data:`PEERS`,
what the CLI hands the harness (``jskel.measure``, which does not import this folder)."""

from __future__ import annotations

from . import mesh_studies
from .skeleton_study import skeleton
from ..probe.study import Peers
from ..probe.study import StudyOptions as StudyOptions
from .mitsuba_image import prepare
from .skeletonizer import RealFitBenchFile, run_real_fit_bench

STUDIES = {
    "embree_mesh": mesh_studies.embree_mesh,
    "embree_same_mesh": mesh_studies.embree_same_mesh,
    "marching_cubes": mesh_studies.marching_cubes,
    "skeleton": skeleton,
}

#: every peer, as the harness's commands take them
PEERS = Peers(STUDIES, mesh_studies.embree_mesh, prepare, (RealFitBenchFile, run_real_fit_bench))

__all__ = ["PEERS", "STUDIES", "StudyOptions"]
