"""Fitting a skeleton's joints and radii to a point cloud (issue 10): the solver chosen for a
problem's size, the stepping loop that records the loss, restarts, and many clouds in one call.
The problem itself (residuals, loss, normalisation) is ``_problem``'s."""

from __future__ import annotations

import sys
import time
from functools import partial
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import checks, numerics, progress
from . import _cover, _solvers
from ._config import SolverConfig
from ._distance import segments_of
from ._problem import (Data, Problem, Sizes, dense_equations, layout_of, loss, normal_equations, normaliser_of, ordered, problem_of, radii_of,
                       residual_count, residuals, unpack)
from ._starts import perturbed


class FitResult(NamedTuple):
    """A fitted skeleton in world units, with the loss after each iteration, iterations, whether the stopping rule was met, seconds (compile apart), the solver's final error, the restarts' losses and when the first iteration was done."""

    joints: np.ndarray
    radii: np.ndarray
    parents: np.ndarray
    history: list  # loss after each iteration (normalised units), the start first
    iterations: int
    converged: bool
    seconds: float
    compile_s: float
    error: float  # the solver's final stopping measure
    restarts: int
    restart_losses: list
    first_iteration_at: float | None = None  # time.time() when the stepping loop's first iteration was done (None: one batched call)
    first_iteration_cpu: float | None = None  # the process's CPU seconds then (time.process_time())
    #: with topology edits (``fitted_in_rounds``): each round's {round, joints, padded_joints, iterations,
    #: seconds, compile_s}; ``iterations``, ``seconds`` and ``compile_s`` above are then their sums
    #: over the rounds (each new topology compiles its own program) and ``history`` the last round's
    rounds: tuple = ()


DENSE_JACOBIAN_MAX = 1 << 24  # entries (residuals x unknowns) up to which jaxopt's LM forms J (64 MiB in float32)


# Jacobian entries (residuals x unknowns) from which ``solver.jacobian: auto`` assembles the
# sparse normal equations. In the fitting benchmark LM took the same steps either way; at
# 10,000 points x 24 unknowns the sparse form was the faster, at 10,000 x 204 many times so, and
# at 10,000 x 2,004 the dense form ran out of memory; at 1,000 x 24 (below the threshold) the two
# took about the same time (docs/choices.md#sparse-from)
SPARSE_FROM = 1 << 17


def jacobian_of(s: SolverConfig, n_res: int, n_par: int) -> str | None:
    """How LM / Gauss-Newton form their steps (``solver.jacobian``, ``auto`` resolved):
    ``dense`` or ``sparse`` normal equations for the project's solver, or ``jaxopt``; None for
    the other solvers."""
    if s.name not in ("lm", "gauss_newton"):
        return None
    if s.jacobian == "auto":
        return "sparse" if n_res * n_par >= SPARSE_FROM else "dense"
    return s.jacobian


class SolverKey(NamedTuple):
    """The solver settings a compiled fit depends on (hashable: a static argument of the fit's
    module-level jitted functions, so a second fit of the same topology and settings, new points
    and starts included, reuses the executables instead of compiling again)."""

    name: str
    maxiter: int
    tol: float
    learning_rate: float
    patience: int
    ftol: float
    jacobian: str | None  # LM / Gauss-Newton: dense or sparse normal equations, or jaxopt's solvers
    dense: bool  # jaxopt's LM forms the Jacobian
    step_limit: float = 0.0  # solver.step_limit


def solver_key(s: SolverConfig, n_res: int, n_par: int) -> SolverKey:
    return SolverKey(s.name, int(s.maxiter), float(s.tol), float(s.learning_rate), int(s.patience), float(s.ftol),
                     jacobian_of(s, n_res, n_par), n_res * n_par <= DENSE_JACOBIAN_MAX, float(s.step_limit))


def step_clip(limit: float, pr: Problem):
    """``clip(x, h)`` of ``solver.step_limit``: each joint's move ``h[3j:3j+3]`` and each radius
    parameter's change scaled down, apart, to at most ``limit`` times that joint's radius at
    ``x`` (normalised units), the direction of each kept."""

    def clip(x, h):
        nj = x.shape[-1] // 4
        cap = limit * radii_of(unpack(x)[1], pr)
        hj = h[: 3 * nj].reshape(nj, 3)
        fj = jnp.minimum(1.0, cap / jnp.maximum(jnp.sqrt(jnp.sum(hj * hj, -1)), jnp.finfo(x.dtype).tiny))
        fr = jnp.minimum(1.0, cap / jnp.maximum(jnp.abs(h[3 * nj :]), jnp.finfo(x.dtype).tiny))
        return jnp.concatenate([(hj * fj[:, None]).reshape(-1), h[3 * nj :] * fr])

    return clip


def stepper(pr: Problem, key: SolverKey) -> _solvers.Stepper:
    """The solver of ``key`` on the problem ``pr`` (built while tracing; nothing compiles here)."""
    system = {"dense": dense_equations, "sparse": normal_equations}.get(key.jacobian)
    normal = (lambda x, p: system(x, p, pr)) if system is not None else None
    return _solvers.make(key.name, lambda x, p: residuals(x, p, pr), lambda x, p: loss(x, p, pr), key.maxiter, key.tol,
                         key.learning_rate, dense=key.dense, normal=normal,
                         clip=step_clip(key.step_limit, pr) if key.step_limit > 0 else None)


def _typed_state(step, x0, args):
    """The solver's initial state with the dtypes an update returns (jaxopt's first update
    turns an int counter into a float), so one executable serves every iteration."""
    st0 = step.init(x0, *args)
    shapes = jax.eval_shape(lambda x, st: step.update(x, st, *args), x0, st0)[1]
    return jax.tree_util.tree_map(lambda a, sh: jnp.asarray(a, sh.dtype), st0, shapes)


#: executables of the fit's programs compiled in this process, by function, static arguments and
#: the arguments' structure, shapes and dtypes (:func:`_executable`); at most :data:`KEEP`
_EXECUTABLES: dict = {}
KEEP = 16


def _executable(fn, *args):
    """``fn.lower(*args).compile()``, kept for the process: ``Lowered.compile`` compiles anew
    each time (only JAX's persistent cache, when on, skips XLA's part), so a later fit of another
    topology of the same sizes (a round of ``_run.fitted_in_rounds``) ran its traced and
    compiled program again. Arguments that are a :class:`Problem` or :class:`SolverKey` are
    static, the others traced."""
    static = tuple(a for a in args if isinstance(a, (Problem, SolverKey)))
    traced = [a for a in args if not isinstance(a, (Problem, SolverKey))]
    leaves, tree = jax.tree_util.tree_flatten(traced)
    k = (fn, static, tree, tuple((np.shape(a), np.dtype(a.dtype), bool(getattr(a, "weak_type", False))) for a in leaves))
    if k not in _EXECUTABLES:
        while len(_EXECUTABLES) >= KEEP:
            _EXECUTABLES.pop(next(iter(_EXECUTABLES)))
        _EXECUTABLES[k] = fn.lower(*args).compile()
    return _EXECUTABLES[k]


@partial(jax.jit, static_argnums=(2, 3))
def _initial(x0, points, pr: Problem, key: SolverKey):
    return _typed_state(stepper(pr, key), x0, (points,))


@partial(jax.jit, static_argnums=(3, 4))
def _update(x, st, points, pr: Problem, key: SolverKey):
    return stepper(pr, key).update(x, st, points)


@partial(jax.jit, static_argnums=(2,))
def _loss(x, points, pr: Problem):
    return loss(x, points, pr)


# solvers whose batches run one fit after another (``lax.map``) instead of in lockstep
# (``vmap``): L-BFGS's line search is a while loop inside every iteration, and in lockstep each
# iteration waits for the batch's slowest search (docs/fitting.md; the batch rows of
# docs/bench_fit_cpu.jsonl are these ``lax.map`` batches)
SEQUENTIAL_BATCH = ("lbfgs",)


def over_batch(name: str, fn):
    """``fn`` mapped over a leading batch axis: ``vmap`` for most solvers, ``lax.map`` (one
    compiled loop, fits in turn) for those in :data:`SEQUENTIAL_BATCH`."""
    if name in SEQUENTIAL_BATCH:
        return lambda *xs: jax.lax.map(lambda a: fn(*a), xs)
    return jax.vmap(fn)


class RunEnd(NamedTuple):
    """How one fit of :func:`run_to_end` ended: the parameters, iterations, final loss, the loss
    after each iteration (``maxiter + 1``, the start first, NaN past the end), the solver's
    stopping measure and the count of iterations in a row whose loss stalled."""

    x: jnp.ndarray
    iterations: jnp.ndarray
    loss: jnp.ndarray
    history: jnp.ndarray
    error: jnp.ndarray
    stalled: jnp.ndarray


def run_to_end(pr: Problem, key: SolverKey, x0, points) -> RunEnd:
    """One fit as a single ``while_loop`` with the stepping loop's stopping rule (the solver's
    criterion, or ``patience`` iterations in a row whose loss fell by less than ``ftol``),
    recording the loss after each iteration; ``vmap`` of it fits many problems in one call. A
    solver with a ``blank`` state makes its initial state with the loop's first pass (iteration
    -1), so the program holds its update once."""
    step = stepper(pr, key)
    if step.blank is not None:
        st0, it0 = jax.tree_util.tree_map(jnp.asarray, step.blank(x0)), -1
        l0 = jnp.asarray(jnp.nan, x0.dtype)
    else:
        st0, it0 = _typed_state(step, x0, (points,)), 0
        # the loss the state holds (every solver but adam's): no further copy of the loss in the loop
        l0 = step.value(st0) if step.value else loss(x0, points, pr)
    hist0 = jnp.full((key.maxiter + 1,), jnp.nan, l0.dtype).at[0].set(l0)

    def cond(c):
        x, st, it, prev, stalled, hist = c
        return (it < 0) | ((it < key.maxiter) & (step.error(st) > key.tol) & (stalled < key.patience))

    def body(c):
        x, st, it, prev, stalled, hist = c
        x, st = step.update(x, st, points)
        cur = step.value(st) if step.value else loss(x, points, pr)
        stalled = jnp.where((it >= 0) & (prev - cur <= key.ftol * jnp.abs(prev)), stalled + 1, 0)
        return x, st, it + 1, cur, stalled, hist.at[it + 1].set(cur)

    x, st, it, cur, stalled, hist = jax.lax.while_loop(cond, body, (x0, st0, jnp.int32(it0), l0, jnp.int32(0), hist0))
    return RunEnd(x, it, cur, hist, step.error(st), stalled)


@partial(jax.jit, static_argnums=(2, 3))
def _solve_starts(xb, points, pr: Problem, key: SolverKey):
    """Every start of ``xb`` (B, P) solved to its end on the same points (:func:`over_batch`)."""
    return over_batch(key.name, lambda x: run_to_end(pr, key, x, points))(xb)


@partial(jax.jit, static_argnums=(2, 3))
def _solve_clouds(x0, points, pr: Problem, key: SolverKey):
    """Each start of ``x0`` (B, P) solved to its end on its own cloud of ``points`` (B, N, 3)."""
    return over_batch(key.name, lambda x, p: run_to_end(pr, key, x, p).x)(x0, points)


def data_of(points, pr: Problem, dtype, seg) -> Data:
    """A fit's data from normalised host ``points`` and topology ``seg`` (``_distance.Segments``),
    as host arrays of ``dtype``: the points, with ``solver.cover`` > 0 their nearest-point index,
    and the topology padded to ``pr.sizes`` (``_problem.layout_of``)."""
    pts = np.asarray(points, dtype)
    return Data(pts, _cover.point_index(pts) if pr.cover > 0 else None, layout_of(seg, pr))


def on_device(data):
    """``data`` (:func:`data_of`'s, or a stack of them) as device arrays, copied as they are
    (``numerics.on_device``: no device program for it)."""
    return jax.tree_util.tree_map(numerics.on_device, data)


def fit_points(points: np.ndarray, joints0, radii0, parents, s: SolverConfig, dtype=np.float32, seed: int = 1,
               perturb: float = 0.0, sizes: Sizes | None = None) -> FitResult:
    """Fit a skeleton of ``parents``' topology to ``points`` from (joints0, radii0): the
    stepping loop records the loss after every iteration; with ``s.restarts > 1`` that many
    starts (the given one and perturbed copies) are solved in one call (:func:`over_batch`,
    each recording its loss curve) and the best is the result: one program, not a second
    compile of the stepping loop (compiling was most of an L-BFGS fit's time when this was
    chosen: docs/choices.md#restarts-one-program). A time budget
    (``max_seconds``) needs the host loop: then the best start is stepped again.

    The program is compiled for ``sizes`` (``_problem.Sizes``; default the topology's own): the
    topology is data, so a later fit of another topology that fits the same sizes (a round of
    ``_run.fitted_in_rounds``) runs the same executables."""
    checks.raise_all(checks.nonfinite("points", points, f"of {len(points)} points"))  # every bad point by index, before any compile
    seg = segments_of(joints0, radii0, parents, "init.skeleton")
    n_par = 4 * len(joints0)
    if len(points) < n_par:
        raise ValueError(f"points: {len(points)} points for {n_par} unknowns (4 per joint of {len(joints0)}); need at least as many points")
    pr = problem_of(seg, s, len(joints0), sizes)
    nz = normaliser_of(points)
    pts = on_device(data_of(nz.points(ordered(points, pr)), pr, dtype, seg))
    key = solver_key(s, residual_count(len(points), pr), 4 * pr.sizes.joints)
    x0 = jnp.asarray(np.asarray(nz.start(np.asarray(joints0, np.float64), np.asarray(radii0, np.float64), pr), dtype))
    t_all = time.perf_counter()
    restart_losses = []
    end, first_at = None, (None, None)
    if s.restarts > 1:
        x0, restart_losses, end, compile_s = _best_start(pr, key, s, nz, (joints0, radii0, parents), pts, seed, perturb)
    if end is not None and s.max_seconds is None:
        it = int(end.iterations)
        x, history, error = end.x, [float(v) for v in np.asarray(end.history)[: it + 1]], float(end.error)
        converged = error <= s.tol or int(end.stalled) >= s.patience
    else:
        x, st, history, it, converged, compile_s, first_at = _stepped(pr, key, s, x0, pts)
        error = float(stepper(pr, key).error(st))
    seconds = time.perf_counter() - t_all - compile_s
    if not np.all(np.isfinite(np.asarray(x))) or not np.isfinite(history[-1]):
        raise ValueError(f"solver.name: {s.name} diverged to a non-finite loss after {it} iterations (try another solver or a smaller learning_rate)")
    if history[-1] > history[0]:  # a finite divergence (Gauss-Newton ran to joints of 1e25 on a 50-segment chain)
        raise ValueError(f"solver.name: {s.name} diverged: the loss rose from {history[0]:.4g} to {history[-1]:.4g} in {it} iterations "
                         "(try lm, a smaller learning_rate or more points)")
    j, r = nz.world(x, pr, len(joints0))
    t_refit = time.perf_counter()
    r = radii_refitted(points, j, r, parents, s)
    seconds += time.perf_counter() - t_refit  # (the host's refit counts as fitting time)
    return FitResult(j, r, np.asarray(parents), history, it, converged, seconds, compile_s, error, s.restarts, restart_losses, *first_at)


def radii_refitted(points, joints, radii, parents, s: SolverConfig) -> np.ndarray:
    """``radii``, or with ``solver.radii_refit`` the radii again with ``joints`` fixed
    (``_radii.refit_radii``, in world units: the scales are fractions of the cloud's extent)."""
    if not s.radii_refit:
        return radii
    from ._radii import refit_radii

    ext = float(np.max(np.ptp(np.asarray(points, np.float64), axis=0)))
    return refit_radii(points, joints, radii, np.asarray(parents), s.loss, s.scale * ext, s.outside, s.min_radius * ext)


def _best_start(pr: Problem, key: SolverKey, s: SolverConfig, nz, start, pts, seed: int, perturb: float):
    """The best of ``s.restarts`` starts (the given ``start`` = (joints, radii, parents) and
    perturbed copies, at least 0.1 of a segment), each solved to its end in one compiled call
    (:func:`over_batch`): (its start, every start's final loss, its :class:`RunEnd`, compile seconds)."""
    joints0, radii0, parents = start
    rng = np.random.default_rng(seed)
    starts = [nz.start(np.asarray(joints0), np.asarray(radii0), pr)]
    for _ in range(s.restarts - 1):
        j, r = perturbed(np.asarray(joints0, np.float64), np.asarray(radii0, np.float64), np.asarray(parents), max(perturb, 0.1), rng)
        starts.append(nz.start(j, r, pr))
    xb = jnp.asarray(np.stack(starts), pts.points.dtype)
    t0 = time.perf_counter()
    solve = _executable(_solve_starts, xb, pts, pr, key)
    compile_s = time.perf_counter() - t0
    ends = solve(xb, pts)
    ls = np.asarray(ends.loss)
    best = int(np.nanargmin(ls))
    return xb[best], [float(v) for v in ls], jax.tree_util.tree_map(lambda a: a[best], ends), compile_s


def _stepped(pr: Problem, key: SolverKey, s: SolverConfig, x0, pts):
    """The stepping loop: one compiled update per iteration on the host, the loss recorded after
    each, stopped by the solver's criterion, ``patience`` iterations of stalled loss or
    ``max_seconds``. Returns (x, state, loss history, iterations, converged, compile seconds,
    ``time.time()`` and the process's CPU seconds when the first iteration was done)."""
    quiet = progress.quiet()
    if not quiet:
        print(f"jskel: compiling the {s.name} solver ...", file=sys.stderr, flush=True)
    step = stepper(pr, key)
    t0 = time.perf_counter()  # compile seconds: the update's program (and the initial state's, where separate; none when cached)
    if step.blank is not None:  # the initial state is one pass of the update's own program
        blank = jax.tree_util.tree_map(jnp.asarray, step.blank(x0))
        upd = _executable(_update, x0, blank, pts, pr, key)
        st0 = upd(x0, blank, pts)[1]
    else:
        st0 = _initial(x0, pts, pr, key)
        upd = _executable(_update, x0, st0, pts, pr, key)
    if step.value is None:  # the loss recorded after each iteration: the state's own where it holds one
        lossf = _executable(_loss, x0, pts, pr)
        value = lambda x, st: float(lossf(x, pts))  # noqa: E731
    else:
        value = lambda x, st: float(step.value(st))  # noqa: E731
    compile_s = time.perf_counter() - t0
    x, st = x0, st0
    history = [value(x, st)]
    converged = False
    it = 0
    stalled = 0
    first_at = (None, None)
    t_loop = time.perf_counter()
    bar = progress.bar(s.maxiter, f"fit ({s.name})", "it")
    for it in range(1, s.maxiter + 1):  # host loop over iterations: one compiled update each
        x, st = upd(x, st, pts)
        history.append(value(x, st))  # float(): the iteration is done
        first_at = (time.time(), time.process_time()) if it == 1 else first_at
        bar.update(1)
        bar.set_postfix(loss=f"{history[-1]:.4g}", refresh=False)
        if s.max_seconds is not None and time.perf_counter() - t_loop > s.max_seconds:
            break  # not converged: the time budget ran out (FitResult.converged says so)
        if float(step.error(st)) <= s.tol:
            converged = True
            break
        # the distance is piecewise smooth (which segment is nearest, rims), so the gradient
        # need not vanish at the optimum: also stop once the loss has stopped falling
        stalled = stalled + 1 if history[-2] - history[-1] <= s.ftol * abs(history[-2]) else 0
        if stalled >= s.patience:
            converged = True
            break
    bar.close()
    return x, st, history, it, converged, compile_s, first_at


def _checked_batch(clouds, j0, r0, parents):
    """The topology of :func:`fit_many`'s starts, after every problem of its inputs, at once
    (``ValueError``): each cloud's non-finite points by cloud and index (``clouds[b]``) and each
    start's bad joints or radii (``init.skeleton[b]``), as :func:`fit_points` names them."""
    lines = []
    for i, c in enumerate(clouds):
        lines += checks.nonfinite(f"clouds[{i}]", c, f"of {len(c)} points")
    seg = None
    for i, (j, r) in enumerate(zip(j0, r0)):
        try:
            got = segments_of(j, r, parents, f"init.skeleton[{i}]")
            seg = got if seg is None else seg
        except ValueError as e:
            lines += getattr(e, "lines", [str(e)])
    checks.raise_all(lines)
    return seg


def _raise_diverged(s: SolverConfig, start, end, finite):
    """ValueError naming every cloud of a batch whose fit diverged: to a non-finite loss or
    skeleton, or to a loss above its start's (as :func:`fit_points` refuses one)."""
    bad = [f"clouds[{i}] (loss {a:.4g} -> {z:.4g})" for i, (a, z, f) in enumerate(zip(start, end, finite))
           if not (f and np.isfinite(z) and z <= a)]
    if bad:
        raise ValueError(f"solver.name: {s.name} diverged on {len(bad)} of {len(end)} clouds: {', '.join(bad)} "
                         "(try lm, a smaller learning_rate or more points)")


def fit_many(clouds, joints0, radii0, parents, s: SolverConfig, dtype=np.float32):
    """Fit one topology to B clouds at once (B, N, 3), each from its own start (B, J, 3) and
    (B, J) or one shared start: every cloud is normalised on the host, then the solver's whole
    run is mapped over the batch in one compiled call (:func:`over_batch`: in lockstep under
    ``vmap``, the batch running until its slowest fit stops, or for L-BFGS one after another).
    Returns (joints (B,J,3), radii (B,J), final losses (B,), seconds, compile seconds). Every
    bad input is one ValueError naming the cloud or start and index, before any compile; a fit
    that diverges (non-finite, or its loss above its start's) is a ValueError naming its cloud."""
    clouds = np.asarray(clouds, np.float64)
    b = clouds.shape[0]
    j0 = np.broadcast_to(np.asarray(joints0, np.float64), (b,) + np.shape(joints0)[-2:])
    r0 = np.broadcast_to(np.asarray(radii0, np.float64), (b,) + np.shape(radii0)[-1:])
    seg = _checked_batch(clouds, j0, r0, parents)
    pr = problem_of(seg, s, j0.shape[1])
    nzs = [normaliser_of(c) for c in clouds]
    pts = on_device(jax.tree_util.tree_map(lambda *a: np.stack(a), *[data_of(nz.points(ordered(c, pr)), pr, dtype, seg) for nz, c in zip(nzs, clouds)]))
    x0 = jnp.asarray(np.stack([nz.start(j, r, pr) for nz, j, r in zip(nzs, j0, r0)]), dtype)
    key = solver_key(s, residual_count(clouds.shape[1], pr), x0.shape[-1])
    t0 = time.perf_counter()
    solve = _executable(_solve_clouds, x0, pts, pr, key)
    compile_s = time.perf_counter() - t0
    t0 = time.perf_counter()
    xs = solve(x0, pts)
    xs.block_until_ready()
    seconds = time.perf_counter() - t0
    of_each = jax.vmap(lambda x, p: loss(x, p, pr))
    losses = np.asarray(of_each(xs, pts))
    _raise_diverged(s, np.asarray(of_each(x0, pts)), losses, np.all(np.isfinite(np.asarray(xs)), axis=-1))
    out = [nz.world(x, pr, j0.shape[1]) for nz, x in zip(nzs, np.asarray(xs))]
    t_refit = time.perf_counter()
    out = [(j, radii_refitted(c, j, r, parents, s)) for c, (j, r) in zip(clouds, out)]
    seconds += time.perf_counter() - t_refit
    return np.stack([o[0] for o in out]), np.stack([o[1] for o in out]), losses, seconds, compile_s
