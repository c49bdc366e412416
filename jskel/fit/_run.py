"""What ``python -m jskel fit FILE --out DIR`` runs (issue 10): read or synthesise the points,
start, solve, and write ``fitted.yaml`` (an experiment ``jskel render`` renders), the skeleton
as SWC and its surface as a PLY mesh (issue 53: output the field's tools read), ``fit.json``
and ``fit.png``."""

from __future__ import annotations

import time
from pathlib import Path

import jax
import numpy as np

from .. import frusta, skeletons
from ..compile.cache import program_counts
from ._config import FitFile
from ._fit import FitResult, fit_points, radii_refitted
from ._measures import measures
from ._points import load_points
from ._starts import perturbed, starting_skeleton


MESH_LEVEL = 2  # fitted.ply: 256 triangles a segment, 32 generators around


def framing_camera(joints, radii, width: int = 480, height: int = 360, fov: float = 40.0) -> dict:
    """A camera section that frames a skeleton (looking from +z, a little above and right)."""
    lo = (joints - radii[:, None]).min(0)
    hi = (joints + radii[:, None]).max(0)
    c = 0.5 * (lo + hi)
    rad = 0.5 * float(np.linalg.norm(hi - lo)) or 1.0
    d = np.array([0.5, 0.35, 1.0])
    d /= np.linalg.norm(d)
    dist = 1.15 * rad / np.tan(np.radians(fov) / 2)
    eye = c + d * dist
    return {"eye": [float(x) for x in eye], "target": [float(x) for x in c], "up": [0.0, 1.0, 0.0], "fov_deg": fov,
            "width": width, "height": height}


def process_started() -> float | None:
    """``time.time()`` at this process's start (Linux: its start in clock ticks after boot, from
    /proc), or None where that cannot be read."""
    import os

    try:
        ticks = int(Path("/proc/self/stat").read_text().rsplit(")", 1)[1].split()[19])
        uptime = float(Path("/proc/uptime").read_text().split()[0])
        return time.time() - uptime + ticks / os.sysconf("SC_CLK_TCK")
    except (OSError, ValueError, IndexError):
        return None


def residual_stats(d: np.ndarray, inlier: float) -> dict:
    a = np.abs(d)
    return {"mean_abs": float(a.mean()), "rms": float(np.sqrt(np.mean(d * d))), "median_abs": float(np.median(a)),
            "p95_abs": float(np.percentile(a, 95)), "max_abs": float(a.max()), "inlier_threshold": inlier,
            "inlier_fraction": float(np.mean(a <= inlier))}


def plot_fit(path: Path, res: FitResult, points: np.ndarray, d: np.ndarray, title: str):
    """Loss over iterations, the residual histogram, and the points (projected on the cloud's
    two principal axes) coloured by |residual| with the fitted skeleton drawn over them."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 3, figsize=(14, 4.2))
    ax[0].semilogy(np.arange(len(res.history)), res.history)
    ax[0].set_xlabel("iteration")
    ax[0].set_ylabel("loss (normalised units)")
    ax[0].set_title("loss")
    ax[1].hist(d, bins=80, color="#4477aa")
    ax[1].set_yscale("log")
    ax[1].set_xlabel("signed distance to the fitted surface (world units)")
    ax[1].set_title("residuals")
    c = points.mean(0)
    _, _, vt = np.linalg.svd(points - c, full_matrices=False)
    pp = (points - c) @ vt[:2].T
    jj = (res.joints - c) @ vt[:2].T
    sc = ax[2].scatter(pp[:, 0], pp[:, 1], c=np.abs(d), s=2, cmap="viridis", vmax=np.percentile(np.abs(d), 95))
    for i, p in enumerate(res.parents):
        if p >= 0:
            ax[2].plot([jj[p, 0], jj[i, 0]], [jj[p, 1], jj[i, 1]], "r-", lw=1.5)
    ax[2].plot(jj[:, 0], jj[:, 1], "r.", ms=6)
    ax[2].set_aspect("equal")
    ax[2].set_title("points by |residual|, fitted skeleton (red)")
    fig.colorbar(sc, ax=ax[2], shrink=0.8)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def run_fit(cfg: FitFile, out: Path, base: Path | None = None) -> dict:
    """Run a fit file: read or synthesise the points, start, solve; write ``fitted.yaml`` (an
    experiment ``jskel render`` renders), ``fitted.swc`` (the skeleton as SWC, ids 1..J, type 0),
    ``fitted.ply`` (the frusta surface as triangles, ``frusta.export_mesh`` at level 2: within
    r (1 - cos(pi / 32)) of the cones), ``fit.json`` and ``fit.png``. Returns fit.json's dict."""
    import json

    import yaml

    dtype = np.float64 if cfg.dtype == "float64" else np.float32
    if dtype == np.float64 and not jax.config.jax_enable_x64:
        raise ValueError("dtype: float64 needs jax_enable_x64 (the CLI's --x64 switches it on)")
    points, pinfo, truth = load_points(cfg.points, base)
    j0, r0, parents, how = starting_skeleton(cfg, points, truth)
    if cfg.init.perturb > 0:
        j0, r0 = perturbed(j0, r0, parents, cfg.init.perturb, np.random.default_rng(cfg.init.seed))
    res, edits, rounds = fitted_in_rounds(cfg.solver, cfg.edits, points, j0, r0, parents, dtype, cfg.init.seed, cfg.init.perturb)
    d, exact, margin = measures(points, res.joints, res.radii, res.parents, cfg.solver.candidates, dtype)
    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "fitted.yaml").write_text(f"# fitted by `jskel fit` ({cfg.solver.name}, {cfg.solver.loss} loss)\n"
                                     + yaml.safe_dump(fitted_experiment(cfg, res), sort_keys=False))
    skeletons.write_swc(out / "fitted.swc", skeletons.from_arrays(res.joints, res.radii, res.parents))  # for neuron/plant tools
    fitted = frusta.FrustaConfig.model_validate(fitted_experiment(cfg, res)["object"])
    mesh = frusta.export_mesh(out / "fitted.ply", fitted, MESH_LEVEL)  # the surface as triangles, for mesh tools
    info = fit_info(cfg, res, how, pinfo, points, d, exact, margin)
    info["surface"] = {k: v for k, v in mesh.items() if k != "path"} | {"file": "fitted.ply"}
    info["rounds"], info["edits"] = rounds, edits
    if truth is not None and len(truth[0]) == len(res.joints) and np.array_equal(truth[2], res.parents):
        info["truth"] = truth_errors(res, truth, pinfo["skeleton_length"])
    from ..render import environment

    info.update({k: v for k, v in environment().items() if k in ("jax", "device", "jskel")})
    (out / "fit.json").write_text(json.dumps(info, indent=2) + "\n")
    plot_fit(out / "fit.png", res, points, d, f"{cfg.name}: {cfg.solver.name} ({cfg.solver.loss}), {len(points)} points, "
                                            f"{res.iterations} iterations, {res.seconds:.2f} s")
    return info


def fitted_in_rounds(solver, edits, points, joints, radii, parents, dtype, seed: int = 1, perturb: float = 0.0):
    """(the last round's FitResult, its iterations, seconds and compile time summed over the
    rounds and each round's in ``FitResult.rounds``; the edits' log; rounds run): fits of the start's topology
    by ``solver`` with topology edits between them (``edits``, ``_topology.edited``), until a
    round edits nothing or ``edits.rounds`` fits are done; one fit without ``edits``. The
    topology is the solver program's data: with ``edits``, each round is compiled for sizes that
    a later, smaller topology can reuse (``_problem.round_sizes``), so rounds share a program
    (each round's ``padded_joints`` says which sizes it ran at); rounds after the first take
    ``edits.later_loss`` where set; ``seed`` and ``perturb`` are the first round's restarts'
    (``fit_points``)."""
    from ._distance import segments_of
    from ._problem import round_sizes, sizes_of
    from ._topology import edited

    rounds = edits.rounds if edits is not None else 1
    log, per = [], []
    ext = float(np.max(np.ptp(points, axis=0)))
    k = 0

    # ``solver.radii_refit`` once, after the last round: the rounds and their edits run as without
    # it (on the trees a refit after every round changed the edits' path: docs/fitting.md)
    each = solver.model_copy(update={"radii_refit": False}) if edits is not None and solver.radii_refit else solver

    def summed(res):
        """``res`` with its iterations, seconds and compile time summed over the rounds so far,
        each round's in ``rounds`` (the last round's alone under-reported a fit with edits), and
        its radii refitted where ``solver.radii_refit`` asks (its time in the last round's)."""
        if each is not solver:
            t = time.perf_counter()
            res = res._replace(radii=radii_refitted(points, res.joints, res.radii, res.parents, solver))
            per[-1]["seconds"] += time.perf_counter() - t
        return res._replace(iterations=sum(r["iterations"] for r in per), seconds=sum(r["seconds"] for r in per),
                            compile_s=sum(r["compile_s"] for r in per), rounds=tuple(per))

    sizes = None
    while True:
        if edits is not None:
            sizes = round_sizes(sizes_of(segments_of(joints, radii, parents, "init.skeleton"), len(joints)), sizes)
        now = each.model_copy(update={"loss": edits.later_loss}) if k > 0 and edits is not None and edits.later_loss else each
        res = fit_points(points, joints, radii, parents, now, dtype, seed=seed, perturb=perturb if k == 0 else 0.0, sizes=sizes)
        k += 1
        per.append({"round": k, "joints": len(res.joints), "padded_joints": sizes.joints if sizes else len(res.joints), "loss": now.loss,
                    "iterations": int(res.iterations), "seconds": float(res.seconds), "compile_s": float(res.compile_s)})
        if k == rounds:
            if edits is not None and edits.final_spurs:
                # the last round's spurs (no fit follows; nothing else is edited)
                j, r, p, done = edited(points, res.joints, res.radii, res.parents, edits, solver.scale * ext, ext, k, spurs_only=True)
                if done:
                    res = res._replace(joints=j, radii=r, parents=p)
                    log.extend(done)
            return summed(res), log, k
        joints, radii, parents, done = edited(points, res.joints, res.radii, res.parents, edits, solver.scale * ext, ext, k)
        log.extend(done)
        if not done:
            return summed(res), log, k


def contracted_and_fitted(points, start, solver, edits, section: str):
    """The benches' start and fit of ``points``: the contraction start of ``start`` (an
    ``EstimateConfig`` whose ``method`` must be ``contraction``; ValueError naming
    ``section``.start.method otherwise), then :func:`fitted_in_rounds`. Returns ((joints, radii,
    parents, info) of the start, (FitResult, edits' log, rounds), seconds {start_s, fit_s,
    compile_s})."""
    import time

    from ._contract import contraction_skeleton

    if start.method != "contraction":
        raise ValueError(f"{section}.start.method: the bench starts from the contraction (got {start.method!r})")
    t = time.perf_counter()
    first = contraction_skeleton(points, start.neighbours, start.ball, start.segment, start.prune, start.max_points)
    start_s = time.perf_counter() - t
    t = time.perf_counter()
    res, log, rounds = fitted_in_rounds(solver, edits, points, *first[:3], np.float32)
    fit_s = time.perf_counter() - t
    return first, (res, log, rounds), {"start_s": round(start_s, 3), "fit_s": round(fit_s, 3), "compile_s": round(res.compile_s, 3)}


def fitted_experiment(cfg: FitFile, res: FitResult) -> dict:
    """The experiment of the fitted skeleton (``fitted.yaml``): a frusta object and a camera,
    the fit file's or one that frames the skeleton."""
    return {
        "name": f"{cfg.name}-fitted",
        "object": {"type": frusta.REPRESENTATION.name, "skeleton": {"joints": res.joints.tolist(), "radii": res.radii.tolist(),
                                                   "parents": [int(p) for p in res.parents]}},
        "camera": cfg.camera.model_dump(mode="json") if cfg.camera is not None else framing_camera(res.joints, res.radii),
    }


def fit_info(cfg: FitFile, res: FitResult, how: str, pinfo: dict, points: np.ndarray, d: np.ndarray, exact: float,
             margin: float | None) -> dict:
    """``fit.json``'s facts of a fit: the solver, the start, the points, the loss curve, the
    residuals ``d`` (world units; inliers within 3 robust scales of the cloud's extent), the
    fraction of points the culling serves ``exact``ly and the fitted skeleton's smallest plane
    ``margin`` (``_measures.measures``)."""
    ext = float(np.max(np.ptp(points, axis=0)))
    started = process_started()
    return {
        "name": cfg.name,
        "solver": cfg.solver.model_dump(mode="json"),
        "start": how,
        "points": pinfo,
        "joints": len(res.joints),
        "segments": int(np.sum(res.parents >= 0)),
        "iterations": res.iterations,
        "converged": res.converged,
        "solver_error": res.error,
        "seconds": res.seconds,  # with edits: summed over the rounds, each round's in "round_fits"
        "compile_s": res.compile_s,
        "round_fits": list(res.rounds),
        # when the stepping loop's first iteration was done (None: the restarts' one batched call),
        # as time.time() and in seconds from the process's start (issue 27's time to a first iteration)
        "first_iteration_at": res.first_iteration_at,
        "first_iteration_s": (res.first_iteration_at - started if res.first_iteration_at is not None and started is not None else None),
        "first_iteration_cpu_s": res.first_iteration_cpu,  # the process's CPU seconds by then (steadier on a shared machine)
        "loss_start": res.history[0],
        "loss_final": res.history[-1],
        "history": res.history,
        "restarts": res.restarts,
        "restart_losses": res.restart_losses,
        "residuals": residual_stats(d, 3.0 * cfg.solver.scale * ext),
        # n . m - sin(half-angle) of the worst shared cutting plane (< 0: a piece is unbounded)
        "plane_margin_min": margin,
        "culling_exact_fraction": exact,
        "dtype": cfg.dtype,
        "programs": program_counts(),  # this process's so far: compiled by XLA, loaded from the persistent cache
    }


def truth_errors(res: FitResult, truth, length: float) -> dict:
    """How far the fit lies from the true skeleton ``truth`` = (joints, radii, parents) of the
    same topology: the worst joint error (world units and of the skeleton's ``length``) and the
    worst relative radius error."""
    err = float(np.max(np.linalg.norm(res.joints - truth[0], axis=1)))
    return {"joint_error_max": err, "joint_error_max_of_length": err / length,
            "radius_error_max_rel": float(np.max(np.abs(res.radii / truth[1] - 1)))}
