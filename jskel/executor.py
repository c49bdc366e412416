"""The executor: a batch function over a ray batch of any size, chunked and compiled once.

:func:`map_chunks` evaluates ``batch_fn(params, rays_chunk)`` in fixed-size chunks so memory
stays bounded and only a few shapes are ever compiled, the same for every batch size in a bucket
(:func:`batch_bucket`, :func:`calls_grouping`; ahead of time, the seconds reported apart from
the run); it chooses the chunk for a memory budget, groups chunks per call, and shards the
rays over devices. It knows nothing of representations: any batch function of (params, Rays)
will do.
"""

from __future__ import annotations

import collections
import time
from dataclasses import dataclass
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .compile import executables
from .progress import quiet
from .compile.call_layout import Layout, call_rays, output_buffers, write_call
from .compile.call_layout import pad_to as _pad_to
from .rays import Rays


def _on_host(rays) -> bool:
    """Whether every array of ``rays`` is a NumPy array or a jax array on CPU devices."""
    for a in rays:
        if isinstance(a, jax.Array):
            if any(d.platform != "cpu" for d in a.devices()):
                return False
        elif not isinstance(a, np.ndarray):
            return False
    return True


class ChunkedResult(NamedTuple):
    """Outputs of :func:`map_chunks` (NumPy pytree) with its timings in seconds."""

    out: object
    compile_s: float
    run_s: float
    memory: dict | None = None  # with a memory budget: the chunk chosen and the bytes of each try


# compiled executables, most recently used last; bounded: a bins program holds several loops and
# branches, and a bench sweeping 48 static settings in one process ran out of memory for LLVM's
# code mappings at the 48th compile when every executable was kept
_COMPILED: "collections.OrderedDict" = collections.OrderedDict()
COMPILED_KEEP = 24


def _signature(args):
    leaves, tree = jax.tree_util.tree_flatten(args)
    return tree, tuple((tuple(np.shape(x)), str(jnp.result_type(x))) for x in leaves)


def program_name(batch_fn: Callable) -> str:
    """The name of ``batch_fn``'s program (``jit(NAME)`` in JAX's logs and ``program_counts``):
    its own, with ``_xG`` for :class:`Grouped` calls of G chunks."""
    if isinstance(batch_fn, Grouped):
        return f"{program_name(batch_fn.batch_fn)}_x{batch_fn.group}"
    return getattr(batch_fn, "__name__", type(batch_fn).__name__)


def _named(batch_fn: Callable, fn: Callable | None = None) -> Callable:
    """``fn`` (default ``batch_fn``) under :func:`program_name`'s name, for ``jax.jit`` (a
    ``shard_map`` or a :class:`Grouped` would otherwise be an unnamed function)."""
    fn = batch_fn if fn is None else fn

    def call(*args):
        return fn(*args)

    call.__name__ = call.__qualname__ = program_name(batch_fn)
    return call


def ray_mesh(devices=None):
    """A 1-D ``jax.sharding.Mesh`` named ``rays`` over ``devices`` (default: every local
    device), or None for a single device."""
    devs = list(jax.local_devices() if devices is None else devices)
    if len(devs) <= 1:
        return None
    return jax.sharding.Mesh(np.array(devs), ("rays",))


def compiler_options(args, mesh=None) -> dict:
    """The XLA options a program over ``args`` compiles with: on CPU devices, those the
    arguments ask for (an argument with a ``compiler_options()`` method, as ``interface.Object``
    and a scene have; the first one asking wins a key), else none. The executable's keys need
    no more: the options follow from the static configuration and jskel's source."""
    devs = jax.local_devices() if mesh is None else list(mesh.devices.flat)
    if devs[0].platform != "cpu":
        return {}
    out: dict = {}
    for a in args:
        ask = getattr(a, "compiler_options", None)
        if callable(ask):
            out = {**ask(), **out}
    return out


def compile_batch_fn(batch_fn: Callable, example_args, mesh=None) -> tuple[Callable, float]:
    """AOT-compile ``jax.jit(batch_fn)`` for ``example_args``; returns (compiled, seconds).

    With a ``mesh`` (see :func:`ray_mesh`) the rays and every output are split on their leading
    axis over the mesh's devices (``shard_map`` with ``P("rays")``), the params replicated: each
    device runs ``batch_fn`` on its share of the chunk. Executables are kept per (function,
    the arguments' tree structure, their shapes and dtypes, devices), so a second call with new
    values of the same shapes compiles nothing and reports 0.0 seconds. Static options travel in
    the tree structure (``interface.Object``'s aux data), so ``batch_fn`` is one module-level
    function per query, not a closure per static setting.
    """
    dev_key = None if mesh is None else tuple(d.id for d in mesh.devices.flat)
    key = (batch_fn, _signature(example_args), jax.config.jax_enable_x64, dev_key)
    hit = _COMPILED.get(key)
    if hit is not None:
        _COMPILED.move_to_end(key)
        return hit, 0.0
    t0 = time.perf_counter()
    if mesh is None:
        fn = jax.jit(_named(batch_fn))
    else:
        from jax.sharding import PartitionSpec as P

        # shard_map: every device runs batch_fn itself on its (chunk,) share, the very program
        # an unsharded run compiles for one chunk, so the results are equal bit for bit
        fn = jax.jit(_named(batch_fn, jax.shard_map(batch_fn, mesh=mesh, in_specs=(P(), P("rays")), out_specs=P("rays"), check_vma=False)))
    # from disk when a previous process stored it (no trace, no compile), else traced, compiled and stored
    compiled = executables.compiled_for(batch_fn, example_args, mesh, lambda: fn.lower(*example_args).compile(compiler_options(example_args, mesh) or None))
    _COMPILED[key] = compiled
    while len(_COMPILED) > COMPILED_KEEP:
        _COMPILED.popitem(last=False)
    return compiled, time.perf_counter() - t0


def compiled_bytes(compiled) -> int | None:
    """Bytes one call of an XLA executable needs on its device (arguments + outputs +
    temporaries, from XLA's memory analysis), or None where the backend does not report it."""
    try:
        m = compiled.memory_analysis()
    except Exception:  # noqa: BLE001 - not every backend implements it
        return None
    if m is None:
        return None
    return int(m.argument_size_in_bytes + m.output_size_in_bytes + m.temp_size_in_bytes)


def chunk_for_budget(batch_fn: Callable, params, rays: Rays, chunk: int, budget: int, mesh=None) -> tuple[int, list[dict]]:
    """The largest chunk (``chunk`` or ``chunk`` halved until it fits) whose compiled call needs
    at most ``budget`` bytes by XLA's memory analysis. Each try compiles (and is cached, so the
    chosen size is not compiled twice); the bytes of the parameters do not shrink with the chunk,
    so a budget below them raises ValueError. Returns (chunk, tries as {chunk, bytes})."""
    tries = []
    c = chunk
    while True:
        ex = Rays(*(_pad_to(a[:c], c) for a in rays))
        compiled, _ = compile_batch_fn(batch_fn, (params, ex), mesh)
        need = compiled_bytes(compiled)
        tries.append({"chunk": c, "bytes": need})
        if need is None or need <= budget:
            return c, tries
        if c == 1:
            raise ValueError(f"render.memory_mb: {budget / 2**20:g} MiB is below what one ray needs ({need / 2**20:.1f} MiB, mostly the scene)")
        # the per-ray part scales with the chunk: jump close to the fit, then halve from there
        fixed = sum(int(np.asarray(x).nbytes) for x in jax.tree_util.tree_leaves(params))
        per_ray = max((need - fixed) / c, 1.0)
        fit = int(max(1, (budget - fixed) // per_ray))
        c = max(1, min(c // 2, 1 << (fit.bit_length() - 1)))


class Live(NamedTuple):
    """A grouped call's batch: its rays and which of its chunks hold any ray (``live``, one
    flag per chunk, a prefix; the others are padding, which :class:`Grouped` skips)."""

    rays: object
    live: object


@dataclass(frozen=True)
class Grouped:
    """``batch_fn`` over up to ``group`` chunks in one call: the rays (group * chunk,) of a
    :class:`Live` batch are viewed as (group, chunk) and a ``fori_loop`` runs ``batch_fn`` on
    each live chunk in turn, inside one compiled program; the padding chunks' outputs are zeros
    and cost nothing. So one program serves every batch of up to ``group`` chunks. Equal (and
    hashing equal) for the same (batch_fn, group), so the executor's compile cache finds the
    executable again without a cache of closures."""

    batch_fn: Callable
    group: int

    def __call__(self, params, batch: Live):
        r = jax.tree_util.tree_map(lambda a: a.reshape((self.group, -1) + a.shape[1:]), batch.rays)
        one = jax.jit(self.batch_fn)  # traced once: eval_shape's trace is jit's cached one
        shapes = jax.eval_shape(one, params, jax.tree_util.tree_map(lambda a: a[0], r))
        acc = jax.tree_util.tree_map(lambda s: jnp.zeros((self.group,) + s.shape, s.dtype), shapes)

        def body(i, acc):
            out = one(params, jax.tree_util.tree_map(lambda a: a[i], r))
            return jax.tree_util.tree_map(lambda a, o: a.at[i].set(o), acc, out)

        out = jax.lax.fori_loop(0, jnp.sum(batch.live, dtype=jnp.int32), body, acc)
        return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)


def grouped(batch_fn: Callable, group: int) -> Callable:
    """``batch_fn`` itself for ``group`` <= 1, else :class:`Grouped` of it."""
    return batch_fn if group <= 1 else Grouped(batch_fn, group)


MIN_GROUPED = 8


def calls_grouping(n_chunks: int, group: int) -> int:
    """Chunks per call for ``n_chunks`` chunks and at most ``group`` per call: 1 below
    ``min(group, MIN_GROUPED)`` chunks (small batches keep the one-chunk program every size
    shares), else the next power of two from ``n_chunks``, at most ``group``: a few programs
    (8, 16, 32, 64, 128 chunks by default) serve every batch size, one serves every batch of more
    than ``group / 2`` chunks; a call's padding chunks are skipped (:class:`Grouped`)."""
    if group <= 1 or n_chunks < min(group, MIN_GROUPED):
        return 1
    return min(group, 1 << (n_chunks - 1).bit_length())


def batch_bucket(n: int) -> int:
    """The rays a batch of ``n`` rays smaller than one chunk is padded to: the next size of the
    form 2^k, 1.25 2^k, 1.5 2^k or 1.75 2^k (at least 8), so images of similar size share a
    program and at most a fifth of the rays traced are padding."""
    if n <= 8:
        return 8
    k = (int(n) - 1).bit_length() - 3  # n - 1 < 8 * 2^k
    return -(-n // (1 << k)) * (1 << k)


def size_bucket(n: int, multiple: int = 1) -> int:
    """The rows a model's table of ``n`` entries (segments, primitives, triangles) is padded
    to, so that a model of similar size shares every program: the next power of two up to 64
    (at least 8), then :func:`batch_bucket`'s sizes (80, 96, 112, 128, 160, ...: a quarter of
    the power of two below, so under a fifth of the rows are padding and the memory grows by
    at most 1.25x, not 2x); rounded up to a multiple of ``multiple`` (a block size). Every
    representation pads its size-dependent tables with this one function; its padding rows
    are inert (never hit, never counted)."""
    n, multiple = int(n), max(1, int(multiple))
    b = max(8, 1 << (max(n, 1) - 1).bit_length()) if n <= 64 else batch_bucket(n)
    return -(-b // multiple) * multiple


def map_chunks(
    batch_fn: Callable,
    params,
    rays: Rays,
    chunk: int = 65536,
    progress: bool | None = None,
    desc: str = "rays",
    devices=None,
    memory_budget: int | None = None,
    group: int = 1,
) -> ChunkedResult:
    """Evaluate ``batch_fn(params, rays_chunk) -> pytree`` over ``rays`` in chunks of ``chunk``.

    The last chunk is padded by repeating the last ray, so exactly one shape is compiled
    (ahead of time; its seconds are reported apart from the run); a batch smaller than one
    chunk is padded to :func:`batch_bucket`'s size, so similar sizes share a program. Chunks are dispatched one
    ahead of the host copy so the device is not idle while the host gathers results. The
    progress bar (tqdm) is shown on a terminal or in a notebook, never in CI
    (``jskel.progress.quiet``), unless ``progress`` says otherwise.

    Returns NumPy arrays of leading size ``rays.size`` with the structure of ``batch_fn``'s
    output. ``devices``: None or one device runs unsharded; a list of devices (or ``"all"``,
    every local device) gives each device ``chunk`` rays per call; the result is the same bit for
    bit as one device with the same ``chunk`` (tested). ``memory_budget`` (bytes per device):
    ``chunk`` is lowered by :func:`chunk_for_budget` until one call fits; the chunk used and
    the bytes it needs are returned in ``memory``.

    ``group`` > 1: up to that many chunks per compiled call (:func:`grouped`, a loop over
    them), where the batch holds at least ``min(group, 8)`` chunks and no memory budget is set;
    the chunks per call are a power of two (:func:`calls_grouping`), the padding chunks skipped,
    neither copied in nor copied back (``call_layout``).
    Each chunk is still computed by ``batch_fn`` alone; what is saved is the host's per-call
    work (slicing, transfers, dispatch): on the CPU the cacti's bins cast at 1024x768 ran faster
    with 16 chunks of 4,096 rays per call than with one, on one device
    (``experiments/bench_scale_cpu_paths.yaml``, docs/choices.md#chunks-per-call).
    """
    n = rays.size
    if n == 0:
        raise ValueError("rays: the batch is empty")
    plan = _plan(batch_fn, params, rays, chunk, devices, memory_budget, group)
    mesh = plan.mesh
    slice_rays, lay, host_s = _slicer(rays, plan)
    first = slice_rays(0)
    compiled, compile_s = compile_batch_fn(plan.batch_fn, (params, first), mesh)
    if plan.memory is not None:
        compile_s += plan.memory["seconds"]  # the tries compiled (the chosen size among them)
    disable = quiet() if progress is None else (not progress)
    t0 = time.perf_counter()
    if mesh is not None:
        # replicated once per call of map_chunks, not once per compiled call: parameters living
        # on one device were copied to the others at every call (300,000 segments: 36 MB a call)
        params = replicated(params, mesh)
    out = _dispatch(compiled, params, first, slice_rays, lay, desc, disable)
    run_s = time.perf_counter() - t0 + host_s
    return ChunkedResult(out, compile_s, run_s, plan.memory)


_REPLICATED: list = []  # [(mesh, tree structure, the leaves given, the replicated pytree)], one entry


def replicated(params, mesh):
    """``params`` placed on every device of ``mesh`` (replicated). The same parameters as the
    last call (the same tree structure and the same JAX arrays, which are immutable) over an
    equal mesh are not copied again: a static scene cast or rendered frame after frame pays the
    copy once, not per frame (docs/choices.md#replicated-params). The last parameters stay
    referenced until the next call. NumPy leaves, which can change in place, are copied every
    time."""
    leaves, tree = jax.tree_util.tree_flatten(params)
    if _REPLICATED:
        m, t, was, out = _REPLICATED[0]
        if m == mesh and t == tree and len(was) == len(leaves) and all(a is b for a, b in zip(was, leaves)):
            return out
    _REPLICATED.clear()
    out = jax.device_put(params, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
    if all(isinstance(x, jax.Array) for x in leaves):
        _REPLICATED.append((mesh, tree, leaves, out))
    return out


class Resident(NamedTuple):
    """A batch laid out as :func:`map_chunks` lays it out and already on its devices
    (:func:`resident_calls`): the batch function as called (:func:`grouped`), the ray mesh
    (None: one device), the calls' layout and each call's rays."""

    batch_fn: Callable
    mesh: object
    layout: Layout
    calls: list

    def host_outputs(self, outs: list):
        """The outputs of every call (in :attr:`calls`' order) as NumPy, in ray order."""
        bufs = output_buffers(outs[0], self.layout)
        for i, o in enumerate(outs):
            write_call(bufs, o, self.layout, i)
        return jax.tree_util.tree_map(lambda b: b[: self.layout.n], bufs)


def resident_calls(batch_fn: Callable, params, rays: Rays, chunk: int = 65536, devices=None, group: int = 1) -> Resident:
    """``rays`` cut into :func:`map_chunks`'s calls (same chunk, chunks per call and device
    order) and placed on the devices ahead of time, for timing the calls alone, with no host
    slicing or copies: how a peer whose rays already live in its own arrays is timed.
    Run them with ``compile_batch_fn(res.batch_fn, (params, res.calls[0]), res.mesh)``."""
    if rays.size == 0:
        raise ValueError("rays: the batch is empty")
    plan = _plan(batch_fn, params, rays, chunk, devices, None, group)
    slice_rays, lay, _ = _slicer(rays, plan)
    put = jax.devices()[0] if plan.mesh is None else jax.sharding.NamedSharding(plan.mesh, jax.sharding.PartitionSpec("rays"))
    calls = [jax.device_put(slice_rays(i), put) for i in range(lay.calls)]
    return Resident(plan.batch_fn, plan.mesh, lay, jax.block_until_ready(calls))


class _Plan(NamedTuple):
    """How :func:`map_chunks` cuts a batch: the ray mesh (None: one device), the rays per
    compiled call, the chunks per call, the batch function as called (:func:`grouped`), and
    the memory budget's report (None without one)."""

    mesh: object
    chunk: int
    per_call: int
    batch_fn: Callable
    memory: dict | None


def _plan(batch_fn: Callable, params, rays: Rays, chunk: int, devices, memory_budget: int | None, group: int) -> _Plan:
    """:func:`map_chunks`'s chunk: at most the batch, lowered to fit ``memory_budget``
    (:func:`chunk_for_budget`, per device) or times the chunks grouped per call, times the
    devices of the mesh."""
    n = rays.size
    chunk = int(min(chunk, batch_bucket(n)))
    mesh = ray_mesh(None if devices == "all" else devices) if devices is not None else None
    memory = None
    if memory_budget is not None:
        t_b = time.perf_counter()
        per_dev = 1 if mesh is None else mesh.size
        c, tries = chunk_for_budget(batch_fn, params, rays, chunk * per_dev, int(memory_budget), mesh)
        chunk = max(1, c // per_dev)
        memory = {"budget_bytes": int(memory_budget), "chunk": chunk, "tries": tries, "seconds": time.perf_counter() - t_b}
    per_call = 1 if memory_budget is not None else calls_grouping(-(-n // (chunk * (1 if mesh is None else mesh.size))), group)
    batch_fn = grouped(batch_fn, per_call)
    chunk *= per_call
    if mesh is not None:
        chunk *= mesh.size  # ``chunk`` rays per device per call
    return _Plan(mesh, chunk, per_call, batch_fn, memory)


def _slicer(rays: Rays, plan: _Plan) -> tuple[Callable, Layout, float]:
    """(slice_rays, layout, seconds): ``slice_rays(i)``, the i-th call's rays laid out for its
    devices (``call_layout.call_rays``: padded to the plan's chunk; a :class:`Live` batch when
    chunks are grouped), the calls' :class:`~jskel.compile.call_layout.Layout`, and the seconds taken
    to view host rays as NumPy."""
    t_host = time.perf_counter()
    if _on_host(rays):  # slicing NumPy costs nothing; slicing a CPU jax array dispatches ops
        rays = Rays(*(np.asarray(a) for a in rays))
    host_s = time.perf_counter() - t_host
    lay = Layout(rays.size, plan.chunk, plan.per_call, 1 if plan.mesh is None else plan.mesh.size)

    def slice_rays(i):
        r = Rays(*(call_rays(a, lay, i) for a in rays))
        # which chunks hold rays: the grouped program skips the others
        return Live(r, lay.live_flags(i)) if lay.per_call > 1 else r

    return slice_rays, lay, host_s


def _dispatch(compiled, params, first, slice_rays: Callable, lay: Layout, desc: str, disable: bool):
    """Host outputs (ray order, leading axis ``lay.n``) of ``compiled`` on each of the
    layout's calls (``slice_rays(i)``, the first given), each call dispatched one ahead of the
    host copy of the previous one so the device is not idle while the host gathers results;
    only the chunks holding rays are copied (``call_layout.write_call``). A tqdm bar unless
    ``disable``."""
    from tqdm.auto import tqdm

    bufs = None
    with tqdm(total=lay.calls, desc=desc, unit="chunk", disable=disable, leave=False) as bar:
        pending = compiled(params, first)
        for i in range(lay.calls):
            nxt = compiled(params, slice_rays(i + 1)) if i + 1 < lay.calls else None
            bufs = output_buffers(pending, lay) if bufs is None else bufs
            write_call(bufs, pending, lay, i)
            bar.update(1)
            pending = nxt
    return jax.tree_util.tree_map(lambda b: b[: lay.n], bufs)
