"""Fitting skeletons of conical frusta to point clouds (issue 10).

Public API:

* :func:`distances` / :func:`signed_distance`: differentiable signed distance from points to a
  skeleton's frusta (``_distance``), with :func:`segments_of` for the static topology, each
  point against its ``candidates`` nearest segments (:func:`culling_exact` certifies it);
  :func:`plane_margins`: how far each shared cutting plane is from leaving a piece unbounded;
* :func:`fit_points`: fit joints and radii of a fixed topology (the project's LM / Gauss-Newton
  on dense normal equations, or for large problems on normal equations assembled from the
  problem's sparsity, ``_normal``; the project's L-BFGS (``_lbfgs``), optax Adam, or jaxopt's LM /
  Gauss-Newton (``solver.jacobian: jaxopt``), all through the adapter in ``_solvers``);
* :func:`pca_chain`, :func:`mst_skeleton`, :func:`contraction_skeleton`: starting skeletons
  estimated from points (``_starts``, ``_contract``), the last finding the topology;
  :func:`fitted_in_rounds`: fits with topology edits between them (``_topology``);
  :func:`read_points`, :func:`load_points`: the cloud (``_points``); the least-squares problem
  in normalised coordinates is ``_problem``'s;
* :func:`run_fit` and :class:`FitFile`: what ``python -m jskel fit FILE --out DIR`` runs."""

from ._bench import FitBenchFile as FitBenchFile
from ._bench import run_fit_bench as run_fit_bench
from ._tree_bench import TreeBenchFile as TreeBenchFile
from ._tree_bench import run_tree_bench as run_tree_bench
from ._config import EditsConfig as EditsConfig
from ._config import EstimateConfig as EstimateConfig
from ._config import FitFile as FitFile
from ._config import SolverConfig as SolverConfig
from ._contract import contraction_skeleton as contraction_skeleton
from ._distance import Segments as Segments
from ._distance import checked_distances as checked_distances
from ._distance import culling_exact as culling_exact
from ._distance import cutting_planes as cutting_planes
from ._distance import plane_margins as plane_margins
from ._distance import distances as distances
from ._distance import geometry as geometry
from ._distance import segments_of as segments_of
from ._distance import signed_distance as signed_distance
from ._fit import FitResult as FitResult
from ._fit import fit_many as fit_many
from ._fit import fit_points as fit_points
from ._measures import point_distances as point_distances
from ._points import load_points as load_points
from ._points import read_points as read_points
from ._points import sample_surface as sample_surface
from ._run import contracted_and_fitted as contracted_and_fitted
from ._run import fitted_in_rounds as fitted_in_rounds
from ._run import run_fit as run_fit
from ._starts import mst_skeleton as mst_skeleton
from ._starts import pca_chain as pca_chain
from ._starts import perturbed as perturbed
from ._solvers import robust_residuals as robust_residuals

__all__ = ["EditsConfig", "contracted_and_fitted", "EstimateConfig", "FitBenchFile", "TreeBenchFile", "run_tree_bench", "FitFile", "FitResult", "SolverConfig", "contraction_skeleton", "fitted_in_rounds", "Segments", "checked_distances", "culling_exact", "cutting_planes", "plane_margins", "distances", "fit_many", "fit_points", "geometry", "load_points", "run_fit_bench",
           "mst_skeleton", "pca_chain", "perturbed", "point_distances", "read_points", "robust_residuals", "run_fit",
           "sample_surface", "segments_of", "signed_distance"]
