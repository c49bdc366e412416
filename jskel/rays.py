"""Ray batches, the pinhole look-at camera, the ``Hit`` record and chunked evaluation.

These types are shared by every representation: a representation's ``intersect_one`` maps one
ray to one ``Hit``; ``jax.vmap`` makes it a batch function and :func:`map_chunks` evaluates that
batch function over a ray batch of any size in fixed-size chunks, so memory stays bounded and
only one shape is ever compiled.

Precision. Cameras are built on the host in float64 and expressed relative to an *anchor* (the
centre of the scene's bounds) before they are cast to the working dtype. A skeleton placed 1e4
away from the world origin is then ray cast in float32 with the precision of one placed at the
origin; only the world position of a hit (anchor + local position) is as coarse as float32 is
at 1e4.
"""

from __future__ import annotations

import collections
import functools
import math
import sys
import time
from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np


class Rays(NamedTuple):
    """A batch of rays ``x(t) = origins + t * directions`` for ``t`` in ``(t_min, t_max]``.

    origins: (N, 3); directions: (N, 3) (unit length from cameras; any non-zero length is
    accepted by intersectors, and ``t`` is measured in units of that length); t_min, t_max: (N,).
    """

    origins: jnp.ndarray
    directions: jnp.ndarray
    t_min: jnp.ndarray
    t_max: jnp.ndarray

    @property
    def size(self) -> int:
        return int(self.origins.shape[0])


#: Hit.flags bits shared by every representation that reports diagnostics
FLAG_OVERFLOW = 1  # a static-capacity list (e.g. candidate primitives) overflowed: result not trusted
FLAG_STEP_CAP = 2  # an iterative search stopped at its step cap before finishing


class Hit(NamedTuple):
    """The nearest intersection of one ray (or a batch: every field gains a leading axis).

    t: () ray parameter, ``+inf`` on a miss.
    position: (3,) hit point in the frame of the rays (``+inf`` on a miss).
    normal: (3,) unit shading normal, zero on a miss.
    uv: (2,) surface parametrization, zero on a miss.
    prim: () int32 primitive id (segment id for frusta), -1 on a miss.
    flags: () int32 bit set of diagnostics (representation-specific, e.g. the implicit tracer's
      candidate overflow and step cap), or None where a representation has none.
    """

    t: jnp.ndarray
    position: jnp.ndarray
    normal: jnp.ndarray
    uv: jnp.ndarray
    prim: jnp.ndarray
    flags: jnp.ndarray | None = None


def masked_hit(t, position, normal, uv, prim, flags=None) -> Hit:
    """A ``Hit`` with the miss sentinels applied wherever ``t`` is not finite: position +inf,
    normal and uv 0, prim -1. Shared by every representation's finishing step."""
    hit = jnp.isfinite(t)
    inf = jnp.asarray(jnp.inf, t.dtype)
    return Hit(
        t=t,
        position=jnp.where(hit, position, inf),
        normal=jnp.where(hit, normal, 0.0),
        uv=jnp.where(hit, uv, 0.0),
        prim=jnp.where(hit, prim, -1).astype(jnp.int32),
        flags=None if flags is None else flags.astype(jnp.int32),
    )


def make_rays(origins, directions, t_min=0.0, t_max=np.inf, dtype=np.float32) -> Rays:
    """Build a ``Rays`` batch from array-likes, broadcasting ``t_min``/``t_max`` to (N,)."""
    o = np.asarray(origins, dtype=np.float64).reshape(-1, 3)
    d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
    if o.shape != d.shape:
        raise ValueError(f"rays: origins {o.shape} and directions {d.shape} differ in shape")
    n = o.shape[0]
    tmin = np.broadcast_to(np.asarray(t_min, dtype=np.float64), (n,))
    tmax = np.broadcast_to(np.asarray(t_max, dtype=np.float64), (n,))
    return Rays(
        jnp.asarray(o, dtype), jnp.asarray(d, dtype), jnp.asarray(tmin, dtype), jnp.asarray(tmax, dtype)
    )


class Camera(NamedTuple):
    """Pinhole look-at camera (host-side, float64).

    eye, target, up: (3,) world coordinates; fov_y_deg: vertical field of view in degrees;
    width, height: image size in pixels.
    """

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray
    fov_y_deg: float
    width: int
    height: int

    def basis(self):
        """Orthonormal camera frame ``(right, true_up, forward)``; raises if ``up`` is degenerate."""
        eye = np.asarray(self.eye, np.float64)
        fwd = np.asarray(self.target, np.float64) - eye
        n = np.linalg.norm(fwd)
        if not n > 0:
            raise ValueError(f"camera.target: equals camera.eye ({list(map(float, eye))})")
        fwd = fwd / n
        up = np.asarray(self.up, np.float64)
        right = np.cross(fwd, up)
        rn = np.linalg.norm(right)
        if not rn > 1e-6 * max(np.linalg.norm(up), 1e-300):
            raise ValueError(
                f"camera.up: {list(map(float, up))} is parallel to the viewing direction "
                f"{list(map(float, np.round(fwd, 6)))}"
            )
        right = right / rn
        true_up = np.cross(right, fwd)
        return right, true_up, fwd

    def rays(self, anchor=None, dtype=np.float32) -> Rays:
        """Primary rays through pixel centres, row-major (row 0 at the top of the image).

        anchor: (3,) world point subtracted from the origins in float64 before casting to
        ``dtype`` (see module docstring). Directions are unit length, t in (0, inf].
        """
        o, d = self.ray_arrays(anchor)
        return make_rays(o, d, 0.0, np.inf, dtype)

    def tiled_rays(self, tile: int, anchor=None, dtype=np.float32) -> Rays:
        """:meth:`rays` in :func:`tile_order`, as host (NumPy) arrays, equal value for value to
        ``permute(self.rays(anchor, dtype), tile_order(...))``. The directions, which depend
        on the camera alone, are cached (an animated frame with a fixed camera makes none);
        the origins are one point, broadcast (the anchor may move from frame to frame)."""
        d = _tiled_directions(self._key(), tile, np.dtype(dtype).name)
        eye = np.asarray(self.eye, np.float64)
        if anchor is not None:
            eye = eye - np.asarray(anchor, np.float64)
        n = d.shape[0]
        o = np.broadcast_to(eye.astype(dtype), (n, 3))
        return Rays(o, d, np.broadcast_to(np.zeros((), dtype), (n,)), np.broadcast_to(np.asarray(np.inf, dtype), (n,)))

    def _key(self) -> tuple:
        return (tuple(map(float, self.eye)), tuple(map(float, self.target)), tuple(map(float, self.up)), float(self.fov_y_deg),
                int(self.width), int(self.height))

    def ray_arrays(self, anchor=None, jitter=None) -> tuple[np.ndarray, np.ndarray]:
        """(origins, directions), both (H*W, 3) float64 NumPy, as :meth:`rays` casts them.

        jitter: None (pixel centres) or (H*W, 2) offsets in pixels (x right, y down) of each
        ray's point in its pixel, e.g. uniform in [-0.5, 0.5) for jittered anti-aliasing."""
        right, up, fwd = self.basis()
        w, h = int(self.width), int(self.height)
        tan_half = math.tan(math.radians(self.fov_y_deg) / 2.0)
        aspect = w / h
        ix, iy = np.meshgrid(np.arange(w, dtype=np.float64) + 0.5, np.arange(h, dtype=np.float64) + 0.5)
        if jitter is not None:
            j = np.asarray(jitter, np.float64).reshape(h, w, 2)
            ix, iy = ix + j[..., 0], iy + j[..., 1]
        px = (ix / w * 2.0 - 1.0) * tan_half * aspect
        py = (1.0 - iy / h * 2.0) * tan_half
        d = fwd[None, :] + px.reshape(-1, 1) * right[None, :] + py.reshape(-1, 1) * up[None, :]
        d /= np.linalg.norm(d, axis=1, keepdims=True)
        eye = np.asarray(self.eye, np.float64)
        if anchor is not None:
            eye = eye - np.asarray(anchor, np.float64)
        return np.broadcast_to(eye, d.shape).copy(), d


@functools.lru_cache(maxsize=4)
def _tiled_directions(key: tuple, tile: int, dtype: str) -> np.ndarray:
    """Unit directions of a camera's rays in :func:`tile_order`, cast to ``dtype`` (read-only)."""
    eye, target, up, fov, w, h = key
    cam = Camera(np.asarray(eye), np.asarray(target), np.asarray(up), fov, w, h)
    d = cam.ray_arrays()[1][tile_order(w, h, tile)].astype(dtype)
    d.flags.writeable = False
    return d


def _morton2(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Interleave the bits of two non-negative int arrays (< 2^16): a 2D Z-order key."""
    def spread(v):
        v = v.astype(np.uint64) & 0xFFFF
        v = (v | (v << 8)) & 0x00FF00FF
        v = (v | (v << 4)) & 0x0F0F0F0F
        v = (v | (v << 2)) & 0x33333333
        v = (v | (v << 1)) & 0x55555555
        return v

    return spread(x) | (spread(y) << np.uint64(1))


@functools.lru_cache(maxsize=8)
def tile_order(width: int, height: int, tile: int) -> np.ndarray:
    """Permutation of row-major pixel indices that lists pixels tile by tile (tile x tile), and
    within a tile in Z-order (Morton order of the pixel's position in its tile).

    Chunks of consecutive rays are then compact on screen, which is what lets a batch-level
    test (one scalar per chunk) skip geometry that no ray of the chunk can reach; with a
    power-of-two tile, every aligned run of 4^j rays inside a tile is a 2^j x 2^j square, which
    is what packet traversal (``jskel.accel.nearest_packet``) wants of its packets.
    """
    ys, xs = np.divmod(np.arange(width * height), width)
    tiles = (ys // tile) * (-(-width // tile)) + xs // tile
    key = tiles.astype(np.uint64) * np.uint64(1 << 32) + _morton2(xs % tile, ys % tile)
    order = np.argsort(key, kind="stable")
    order.flags.writeable = False  # cached (lru_cache): shared by every caller
    return order


@functools.lru_cache(maxsize=8)
def tile_inverse(width: int, height: int, tile: int) -> np.ndarray:
    """The inverse permutation of :func:`tile_order` (cached): ``a[tile_inverse(...)]`` puts
    values computed in tile order back in row-major order."""
    order = tile_order(width, height, tile)
    inv = np.empty_like(order)
    inv[order] = np.arange(order.size)
    inv.flags.writeable = False
    return inv


def permute(rays: Rays, order: np.ndarray) -> Rays:
    """The rays in the order of the index array ``order`` (e.g. :func:`tile_order`)."""
    return Rays(*(a[order] for a in rays))


def _pad_to(x, n: int):
    pad = n - x.shape[0]
    if pad == 0:
        return x
    xp = np if isinstance(x, np.ndarray) else jnp
    filler = xp.broadcast_to(x[-1:], (pad,) + x.shape[1:])
    return xp.concatenate([x, filler], axis=0)


def _on_host(rays) -> bool:
    """Whether every array of ``rays`` is a NumPy array or a jax array on CPU devices."""
    for a in rays:
        if isinstance(a, jax.Array):
            if any(d.platform != "cpu" for d in a.devices()):
                return False
        elif not isinstance(a, np.ndarray):
            return False
    return True


def _interleave(tree, a: int, b: int):
    """Leading axis (a * b * c,) viewed as (a, b, c) and transposed to (b, a, c), for NumPy
    arrays. With a call's rays as (chunks, devices, chunk) this gives device d the chunks d,
    d + D, d + 2 D, ... instead of one contiguous run of the image: in screen-tile order a run
    may be mostly sky on one device and mostly scene on the other, and the call waits for the
    slower (``(devices, chunks)`` back again undoes it)."""

    def one(x):
        c = x.shape[0] // (a * b)
        return np.swapaxes(x.reshape((a, b, c) + x.shape[1:]), 0, 1).reshape(x.shape)

    return jax.tree_util.tree_map(one, tree)


def compact_map(fn: Callable, need: jnp.ndarray, rays: Rays, base, lanes: int):
    """``base`` with the entries where ``need`` (N,) holds replaced by ``fn(rays_sub)``, where
    ``fn`` maps a Rays batch of ``lanes`` rays to a pytree like ``base``'s rows. ``rays`` may
    be any pytree of arrays with leading axis N (``fn`` then gets the same pytree of ``lanes``
    rows).

    Compaction, not masking (wavefront style): the needed rays are gathered into dense
    sub-batches of ``lanes`` and a ``while_loop`` runs only as many sub-batches as there are
    needed rays (none when none is needed), then the results are scattered back. Under vmap a
    per-ray ``cond`` would run ``fn`` on every ray. The needed rows are found with popcounts
    (``accel._bins.first_set``), not ``jnp.nonzero``'s prefix sum over N."""
    from .accel import first_set, pack_bits

    n = need.shape[0]
    lanes = min(lanes, n)
    order, count = first_set(pack_bits(need), n)
    order = jnp.concatenate([jnp.minimum(order, n - 1), jnp.zeros((lanes,), jnp.int32)])

    def body(state):
        j, acc = state
        lane = j * lanes + jnp.arange(lanes, dtype=jnp.int32)
        idx = jax.lax.dynamic_slice(order, (j * lanes,), (lanes,))
        out = fn(jax.tree_util.tree_map(lambda a: a[idx], rays))
        dst = jnp.where(lane < count, idx, n)  # n: dropped by the scatter
        acc = jax.tree_util.tree_map(lambda a, o: a.at[dst].set(o.astype(a.dtype), mode="drop"), acc, out)
        return j + 1, acc

    return jax.lax.while_loop(lambda st: st[0] * lanes < count, body, (jnp.int32(0), base))[1]


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


def ray_mesh(devices=None):
    """A 1-D ``jax.sharding.Mesh`` named ``rays`` over ``devices`` (default: every local
    device), or None for a single device."""
    devs = list(jax.local_devices() if devices is None else devices)
    if len(devs) <= 1:
        return None
    return jax.sharding.Mesh(np.array(devs), ("rays",))


def compile_batch_fn(batch_fn: Callable, example_args, mesh=None) -> tuple[Callable, float]:
    """AOT-compile ``jax.jit(batch_fn)`` for ``example_args``; returns (compiled, seconds).

    With a ``mesh`` (see :func:`ray_mesh`) the rays and every output are split on their leading
    axis over the mesh's devices (``shard_map`` with ``P("rays")``), the params replicated: each
    device runs ``batch_fn`` on its share of the chunk. Executables are kept per (function,
    argument shapes and dtypes, devices), so a second call with new values of the same shapes
    compiles nothing and reports 0.0 seconds.
    """
    dev_key = None if mesh is None else tuple(d.id for d in mesh.devices.flat)
    key = (batch_fn, _signature(example_args), jax.config.jax_enable_x64, dev_key)
    hit = _COMPILED.get(key)
    if hit is not None:
        _COMPILED.move_to_end(key)
        return hit, 0.0
    t0 = time.perf_counter()
    if mesh is None:
        fn = jax.jit(batch_fn)
    else:
        from jax.sharding import PartitionSpec as P

        # shard_map: every device runs batch_fn itself on its (chunk,) share, the very program
        # an unsharded run compiles for one chunk, so the results are equal bit for bit
        fn = jax.jit(jax.shard_map(batch_fn, mesh=mesh, in_specs=(P(), P("rays")), out_specs=P("rays"), check_vma=False))
    compiled = fn.lower(*example_args).compile()
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


_GROUPED: dict = {}


def grouped(batch_fn: Callable, group: int) -> Callable:
    """``batch_fn`` over ``group`` chunks in one call: the rays (group * chunk,) are viewed as
    (group, chunk) and ``lax.map`` runs ``batch_fn`` on each chunk in turn, inside one compiled
    program. The same function object is returned for the same (batch_fn, group), so compiled
    executables are reused."""
    if group <= 1:
        return batch_fn
    key = (batch_fn, group)
    if key not in _GROUPED:

        def fn(params, rays):
            r = type(rays)(*(a.reshape((group, -1) + a.shape[1:]) for a in rays))
            out = jax.lax.map(lambda rr: batch_fn(params, rr), r)
            return jax.tree_util.tree_map(lambda x: x.reshape((-1,) + x.shape[2:]), out)

        _GROUPED[key] = fn
    return _GROUPED[key]


MIN_GROUPED = 8


def calls_grouping(n_chunks: int, group: int) -> int:
    """Chunks per call for ``n_chunks`` chunks and at most ``group`` per call: 1 below
    ``min(group, MIN_GROUPED)`` chunks (small batches keep the one-chunk program every size
    shares), else the fewest calls with their chunks spread evenly (padding under one chunk per
    call)."""
    if group <= 1 or n_chunks < min(group, MIN_GROUPED):
        return 1
    calls = -(-n_chunks // group)
    return -(-n_chunks // calls)


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
    (ahead of time; its seconds are reported apart from the run). Chunks are dispatched one
    ahead of the host copy so the device is not idle while the host gathers results. The
    progress bar (tqdm) is shown only on a terminal unless ``progress`` forces it.

    Returns NumPy arrays of leading size ``rays.size`` with the structure of ``batch_fn``'s
    output. ``devices``: None or one device runs unsharded; a list of devices (or ``"all"``,
    every local device) gives each device ``chunk`` rays per call; the result is the same bit for
    bit as one device with the same ``chunk`` (tested). ``memory_budget`` (bytes per device):
    ``chunk`` is lowered by :func:`chunk_for_budget` until one call fits; the chunk used and
    the bytes it needs are returned in ``memory``.

    ``group`` > 1: up to that many chunks per compiled call (:func:`grouped`, a ``lax.map``
    over them), where the batch holds at least ``group`` chunks and no memory budget is set.
    Each chunk is still computed by ``batch_fn`` alone; what is saved is the host's per-call
    work (slicing, transfers, dispatch): on the 2-core CPU the cacti's bins cast at 1024x768
    took 0.103 s with 16 chunks of 4,096 rays per call against 0.125 s with one, on one device
    (``experiments/bench_scale_cpu_paths.yaml``).
    """
    from tqdm.auto import tqdm

    n = rays.size
    if n == 0:
        raise ValueError("rays: the batch is empty")
    chunk = int(min(chunk, n))
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
    n_chunks = -(-n // chunk)

    t_host = time.perf_counter()
    if _on_host(rays):  # slicing NumPy costs nothing; slicing a CPU jax array dispatches ops
        rays = Rays(*(np.asarray(a) for a in rays))
    host_s = time.perf_counter() - t_host
    spread = mesh is not None and mesh.size > 1 and per_call > 1

    def slice_rays(i):
        lo = i * chunk
        r = Rays(*(_pad_to(a[lo : lo + chunk], chunk) for a in rays))
        return _interleave(r, per_call, mesh.size) if spread else r

    first = slice_rays(0)
    compiled, compile_s = compile_batch_fn(batch_fn, (params, first), mesh)
    if memory is not None:
        compile_s += memory["seconds"]  # the tries compiled (the chosen size among them)
    disable = (not sys.stderr.isatty()) if progress is None else (not progress)
    outs = []
    t0 = time.perf_counter()
    if mesh is not None:
        # replicated once per call of map_chunks, not once per compiled call: parameters living
        # on one device were copied to the others at every call (300,000 segments: 36 MB a call)
        params = jax.device_put(params, jax.sharding.NamedSharding(mesh, jax.sharding.PartitionSpec()))
    with tqdm(total=n_chunks, desc=desc, unit="chunk", disable=disable, leave=False) as bar:
        pending = compiled(params, first)
        for i in range(1, n_chunks + 1):
            nxt = compiled(params, slice_rays(i)) if i < n_chunks else None
            got = jax.tree_util.tree_map(np.asarray, pending)
            outs.append(_interleave(got, mesh.size, per_call) if spread else got)
            bar.update(1)
            pending = nxt
    run_s = time.perf_counter() - t0 + host_s
    out = jax.tree_util.tree_map(lambda *xs: np.concatenate(xs, axis=0)[:n], *outs)
    return ChunkedResult(out, compile_s, run_s, memory)
