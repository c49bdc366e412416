"""The fit file (``python -m jskel fit FILE --out DIR``), validated by pydantic."""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import Field, model_validator

from ..config import CameraConfig, StrictModel
from ..frusta import SkeletonConfig

Frac = Annotated[float, Field(ge=0.0, le=1.0)]


class SyntheticConfig(StrictModel):
    """Points sampled uniformly on a known skeleton's surface, with Gaussian noise of standard
    deviation ``noise`` x the skeleton's length (sum of segment lengths), and a fraction
    ``outliers`` of the points replaced by uniform samples in the bounding box grown by 20%."""

    skeleton: SkeletonConfig
    """The true skeleton the points are sampled from."""
    count: Annotated[int, Field(ge=1, le=10_000_000)] = 2000
    """Number of points."""
    noise: Annotated[float, Field(ge=0.0, le=1.0)] = 0.01
    """Standard deviation of the Gaussian noise, a fraction of the skeleton's length."""
    outliers: Frac = 0.05
    """Fraction of the points replaced by uniform samples in the grown bounding box."""
    seed: int = 0
    """Random seed of the sampling."""


class PointsConfig(StrictModel):
    """A point cloud: a ``file`` (.npy (N,3), .xyz / .txt (x y z per line), .ply) or
    ``synthetic`` points. ``nonfinite``: NaN or inf points are rejected (an error naming
    each bad point's index and value, the count and the first five where many) or dropped
    (counted in fit.json)."""

    file: str | None = None
    """A point file: .npy (N, 3), .xyz / .txt (x y z per line) or .ply."""
    synthetic: SyntheticConfig | None = None
    """Points sampled from a known skeleton instead of a file."""
    nonfinite: Literal["reject", "drop"] = "reject"
    """NaN or inf points: an error naming them, or dropped (counted in fit.json)."""

    @model_validator(mode="after")
    def _one_source(self):
        if (self.file is None) == (self.synthetic is None):
            raise ValueError("give exactly one of 'file' and 'synthetic'")
        return self


class EstimateConfig(StrictModel):
    """A skeleton estimated from the points. ``contraction``: the topology from the points
    themselves (Laplacian contraction, then balls joined where their points are neighbours:
    ``jskel/fit/_contract.py``). ``pca_chain``: ``segments`` segments along the
    cloud's principal axis (a single tube, roughly straight). ``mst``: a minimum spanning tree
    over the centroids of occupied voxels of edge ``voxel`` (x the cloud's extent), simplified
    to joints about ``segment`` (x extent) apart, twigs shorter than ``prune`` voxels cut; needs
    voxels wider than the tubes and narrower than the gaps between branches."""

    method: Literal["pca_chain", "mst", "contraction"] = "pca_chain"
    """A chain along the principal axis, a minimum spanning tree over occupied voxels, or the
    points contracted onto curves by their Laplacian (Cao et al. 2010), whose branches the
    skeleton follows."""
    segments: Annotated[int, Field(ge=1, le=4096)] = 5
    """``pca_chain``: number of segments."""
    voxel: Annotated[float, Field(gt=0.0, le=1.0)] = 0.08
    """``mst``: voxel edge, a fraction of the cloud's extent."""
    segment: Annotated[float, Field(gt=0.0, le=1.0)] = 0.15
    """``mst``: spacing of the simplified joints, a fraction of the cloud's extent."""
    prune: Annotated[float, Field(ge=0.0, le=1000.0)] = 3.0
    """``mst``: twigs shorter than this many voxel edges are cut; ``contraction``: this many balls."""
    neighbours: Annotated[int, Field(ge=3, le=64)] = 10
    """``contraction``: the nearest points whose mean the Laplacian pulls each point towards."""
    ball: Annotated[float, Field(gt=0.0, le=1.0)] = 0.04
    """``contraction``: radius of the balls that group the contracted points into nodes, a
    fraction of the cloud's extent (smaller than the gaps between branches)."""
    max_points: Annotated[int, Field(ge=16, le=1_000_000)] = 20000
    """``contraction``: larger clouds are first reduced to about this many points by a voxel grid."""


class InitConfig(StrictModel):
    """The starting skeleton: ``skeleton`` (given) or ``estimate``; with ``synthetic`` points
    and neither, the true skeleton. ``perturb``: joints moved by a random vector of that
    fraction of the mean segment length, radii scaled by 1 +- perturb (random signs)."""

    skeleton: SkeletonConfig | None = None
    """A given starting skeleton; not with ``estimate``."""
    estimate: EstimateConfig | None = None
    """Estimate the starting skeleton from the points."""
    perturb: Frac = 0.0
    """Random perturbation of the start: joints by this fraction of the mean segment length, radii by 1 +- it."""
    seed: int = 1
    """Random seed of the perturbation."""

    @model_validator(mode="after")
    def _not_both(self):
        if self.skeleton is not None and self.estimate is not None:
            raise ValueError("give 'skeleton' or 'estimate', not both")
        return self


class SolverConfig(StrictModel):
    """``name``: lm (Levenberg-Marquardt), gauss_newton (both the project's, or jaxopt's), lbfgs (``_lbfgs``) or adam (optax).
    ``loss``: l2, huber, cauchy or geman_mcclure (bounded), with ``scale`` a fraction of the cloud's extent.
    ``smoothness``: weight of the joints' second differences along chains. ``restarts``: fits
    from that many perturbed starts in one call (``_fit.over_batch``), the best kept. ``validity``: weight of the
    penalty that keeps every shared cutting plane cutting both its cones in ellipses and facing
    its segments (``_distance.plane_margins``), so no piece becomes an unbounded wedge.
    ``candidates``: each point is measured against its that many nearest segments (by a lower
    bound; 0: all); fit.json reports the fraction of points for which that is certainly exact.
    ``jacobian`` (lm, gauss_newton): the project's Levenberg-Marquardt / Gauss-Newton
    (``_solvers.normal_solver``) on ``dense`` normal equations (the Jacobian by forward mode,
    ``_problem.dense_equations``) or ``sparse`` ones assembled from the problem's sparsity
    (``_normal``: each point depends on one segment's four joints); ``auto``, sparse from
    ``_fit.SPARSE_FROM`` Jacobian entries (residuals x unknowns, 131,072: about 5,000 points on
    a 5-segment chain), where it is as fast or faster, dense below; ``jaxopt``, jaxopt's solvers
    on the residuals (the same algorithm, the reference; larger programs, slower to compile)."""

    name: Literal["lm", "gauss_newton", "lbfgs", "adam"] = "lm"
    """The solver: Levenberg-Marquardt, Gauss-Newton, L-BFGS (strong Wolfe line search) or Adam (optax)."""
    loss: Literal["l2", "huber", "cauchy", "geman_mcclure"] = "huber"
    """Robust loss on the point distances."""
    scale: Annotated[float, Field(gt=0.0, le=1.0)] = 0.01
    """The robust loss's scale, a fraction of the cloud's extent."""
    maxiter: Annotated[int, Field(ge=1, le=100_000)] = 100
    """Most iterations."""
    tol: Annotated[float, Field(gt=0.0)] = 1e-6
    """The solver's own stopping criterion (gradient norm, normalised units)."""
    ftol: Annotated[float, Field(ge=0.0)] = 1e-6
    """Or stop when the loss falls by less than this fraction ..."""
    patience: Annotated[int, Field(ge=1, le=100_000)] = 10
    """... for this many iterations in a row."""
    step_limit: Annotated[float, Field(ge=0.0, le=100.0)] = 0.0
    """``lm`` / ``gauss_newton`` with the project's normal equations: each joint moves, and each
    radius changes, by at most this many times the joint's radius a step (0: no limit). The
    Gauss-Newton step from a long chain's start moved a few joints by several segments and a
    third of the radii by over a quarter; LM's one damping then grew until no radius moved
    (docs/fitting.md). Off by default until the benches of branching and real shapes have run
    with it."""
    radii_refit: bool = False
    """After the solver stops: the radii again with the joints fixed, by robust linear least
    squares of the points' radial offsets from the fitted cones (``_radii.refit_radii``, the
    fit's loss, scale and ``outside`` weight). The loss history and ``loss_final`` are the
    solver's, before it. Every fit of a file or a batch; with ``edits``, once after the last
    round (the rounds and their edits as without it)."""
    learning_rate: Annotated[float, Field(gt=0.0)] = 0.01
    """``adam``: step size."""
    smoothness: Annotated[float, Field(ge=0.0)] = 0.0
    """Weight of the joints' second differences along chains."""
    restarts: Annotated[int, Field(ge=1, le=4096)] = 1
    """Fits from that many perturbed starts in one call; the best is kept."""
    min_radius: Annotated[float, Field(ge=0.0, le=1.0)] = 1e-4
    """Smallest radius, a fraction of the extent (radii = min + s softplus(u / s), ``_problem.RADIUS_SOFTNESS``)."""
    candidates: Annotated[int, Field(ge=0, le=4096)] = 8
    """Nearest segments each point is measured against (0: all)."""
    block: Annotated[int, Field(ge=0, le=65536)] = 64
    """Points (near ones together) that first share a list of ``block_candidates`` segments to
    choose their ``candidates`` from, where the skeleton has more segments than that and
    points x segments reach ``_problem.BLOCK_FROM`` (2^20); each point's choice stays its own
    (0: every point chooses among every segment; ``_distance._candidates``)."""
    block_candidates: Annotated[int, Field(ge=1, le=4096)] = 32
    """Segments in a block's list (more than ``candidates``)."""
    max_seconds: Annotated[float, Field(gt=0.0)] | None = None
    """Stop the stepping loop after this long (reported); unset: no limit."""
    validity: Annotated[float, Field(ge=0.0)] = 1.0
    """Weight of the penalty keeping shared cutting planes cutting ellipses (0: off)."""
    outside: Annotated[float, Field(gt=0.0, le=1e6)] = 1.0
    """Weight of a point outside the fitted surface against one inside at the same distance
    (the squared residual's). Above 1 the surface wraps the points: for points sampled on a
    closed surface (a mesh's vertices, a scan), whose skeleton should enclose them rather than
    halve their noise. With ``l2``, radii then sit at the ``outside / (1 + outside)``
    expectile of the points' radial spread instead of its mean."""
    cover: Annotated[float, Field(ge=0.0, le=1e6)] = 0.0
    """Weight of the term from the surface back to the points (0: off): samples on every
    segment's cone pulled towards their nearest point, together weighing ``cover`` times the
    points (``jskel/fit/_cover.py``). For points that cover the whole surface (a mesh, a scan
    from every side): a surface may otherwise grow where no point is (a free tip into outliers,
    a joint swollen to enclose a side branch)."""
    jacobian: Literal["auto", "dense", "sparse", "jaxopt"] = "auto"
    """``lm`` / ``gauss_newton``: dense or sparse normal equations, ``auto`` (sparse for big problems), or jaxopt's solvers."""

    @model_validator(mode="after")
    def _block_list_longer(self):
        if self.block > 0 and self.candidates > 0 and self.block_candidates <= self.candidates:
            raise ValueError(f"block_candidates: {self.block_candidates} must exceed candidates ({self.candidates}) "
                             "while block > 0 (or set block: 0)")
        return self

    @model_validator(mode="after")
    def _step_limit_needs_the_normal_solver(self):
        if self.step_limit > 0 and (self.name not in ("lm", "gauss_newton") or self.jacobian == "jaxopt"):
            raise ValueError(f"step_limit: {self.step_limit} caps the steps of lm / gauss_newton on the project's normal "
                             f"equations only (got name {self.name!r}, jacobian {self.jacobian!r}; set step_limit: 0)")
        return self


class EditsConfig(StrictModel):
    """Topology edits between rounds of the fit (``jskel/fit/_topology.py``): after each round
    but the last, tips that fewer than ``prune_points`` points are nearest to and tip branches
    ending within ``spur_radii`` radii of the tube they leave are pruned, two segments leaving
    a joint side by side (far joints within ``zip_radii`` radii) are zipped, joints thinner than
    ``neck_ratio`` of every neighbour, segments shorter than ``merge_length`` (x extent) or
    ``merge_radii`` radii and joints where a chain turns by less
    than ``merge_angle`` degrees are merged, and segments whose points lie further than
    ``split_residual`` robust scales from them (root mean square) are split; after the last
    round, optionally its spurs alone (``final_spurs``); every edit is logged in fit.json. The
    rounds stop early when a round edits nothing."""

    rounds: Annotated[int, Field(ge=1, le=20)] = 3
    """Fits in all, with edits between them."""
    prune_points: Annotated[int, Field(ge=0, le=1_000_000)] = 5
    """A tip segment with fewer nearest points is pruned."""
    merge_length: Annotated[float, Field(ge=0.0, le=1.0)] = 0.01
    """A segment shorter than this fraction of the extent is merged into its parent joint."""
    merge_radii: Annotated[float, Field(ge=0.0, le=100.0)] = 2.0
    """A segment shorter than this many times its mean radius, whose far joint has at most one
    child, is merged too (a frustum shorter than its width: its cutting planes turn with every
    small move of its joints)."""
    spur_radii: Annotated[float, Field(ge=0.0, le=100.0)] = 1.0
    """A tip branch (from a tip to the first joint with another branch) whose tip lies within
    this many radii of another segment's axis at that joint is pruned whole: a bump of the tube
    it leaves, not a branch."""
    zip_radii: Annotated[float, Field(ge=0.0, le=100.0)] = 0.0
    """Two segments leaving one joint whose far joints lie closer than this many times their
    mean radius are one tube traced twice: the child one is merged into the other (0: never,
    the default; docs/fitting.md has the tree benchmark with 1)."""
    final_spurs: bool = False
    """After the last round, its spurs are pruned (nothing else is edited, and no fit follows:
    removing a twig leaves the rest of the skeleton as fitted), each logged like a round's. Off
    by default: in the tree benchmark it removed one or two extra tips of the grown trees but
    also the side branch of one of the 5-segment tree's 10 draws (docs/fitting.md)."""
    neck_ratio: Annotated[float, Field(ge=0.0, le=1.0)] = 0.5
    """A joint whose radius is below this fraction of every neighbour's (a neck) is merged into
    its nearest neighbour: a connection the fit has hidden inside the tubes around it."""
    merge_angle: Annotated[float, Field(ge=0.0, le=90.0)] = 10.0
    """A joint where its chain turns by less than this (degrees) is removed."""
    split_residual: Annotated[float, Field(gt=0.0)] = 3.0
    """A segment whose points' RMS distance exceeds this many ``solver.scale`` x extent is split."""
    later_loss: Literal["l2", "huber", "cauchy", "geman_mcclure"] | None = None
    """The robust loss of every round after the first (unset: ``solver.loss`` in all). A
    redescending loss (``geman_mcclure``) once the first round has found the branches: a free
    tip's cap no longer gains by reaching towards outliers (docs/fitting.md)."""


class FitFile(StrictModel):
    """A fit: points, a start, a solver; the output experiment uses ``camera`` (framed on the
    fitted skeleton when omitted)."""

    name: str = "fit"
    """The fit's name (the output experiment's)."""
    points: PointsConfig
    """The point cloud."""
    init: InitConfig = InitConfig()
    """The starting skeleton."""
    solver: SolverConfig = SolverConfig()
    """The solver and its loss."""
    edits: EditsConfig | None = None
    """Topology edits between rounds of the fit; unset: one fit of the start's topology."""
    camera: CameraConfig | None = None
    """The output experiment's camera; unset: framed on the fitted skeleton."""
    dtype: Literal["float32", "float64"] = "float32"
    """Precision of the fit."""
