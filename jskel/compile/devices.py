"""How many XLA host (CPU) devices this process gets: an explicit call, never an import side effect.

On a CPU, ``render.devices: all`` shards a render's chunks over XLA host devices the way it shards
them over GPUs; each device runs whole chunks, where XLA's own threading inside one chunk's small
operations gains little (with 16 chunks per call the cacti's cast at 1024x768 ran faster on two
devices than on one, ``experiments/bench_scale_cpu_paths.yaml``, docs/performance.md,
docs/choices.md#host-devices). JAX makes one
host device unless asked for more before its backend starts, so the CLI calls
:func:`use_host_devices` first thing; in Python, call it right after ``import jskel`` (before any
JAX operation) to get the same sharding::

    import jskel
    jskel.use_host_devices()   # one per core; or use_host_devices(4)
"""

from __future__ import annotations

import os


def _count_from_env(name: str = "JSKEL_HOST_DEVICES") -> int | None:
    want = os.environ.get(name)
    if not want:
        return None
    if not want.strip().isdigit() or int(want) < 1:
        raise ValueError(f"{name}: {want!r} is not a positive integer (XLA host devices to make)")
    return int(want)


def cores() -> int:
    """CPU cores this process may run on."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def use_host_devices(count: int | None = None) -> int:
    """Ask JAX for ``count`` host devices (default: ``JSKEL_HOST_DEVICES`` if set, else one per
    core). Returns the count JAX will use. Changes nothing, and returns JAX's count, when
    ``XLA_FLAGS`` already names a count or JAX's backend has already started (a notebook that
    ran a JAX operation first keeps its devices). A count below 1 is a ``ValueError``."""
    import jax

    if count is not None and (not isinstance(count, int) or count < 1):
        raise ValueError(f"use_host_devices: count {count!r} is not a positive integer")
    n = count if count is not None else (_count_from_env() or cores())
    if "xla_force_host_platform_device_count" in os.environ.get("XLA_FLAGS", ""):
        return len(jax.devices("cpu"))
    try:
        jax.config.update("jax_num_cpu_devices", n)
    except RuntimeError:  # the backend has started: its device count is fixed
        return len(jax.devices("cpu"))
    return n
