"""jskel: ray casting skeletal and detail surface representations in JAX."""

__version__ = "0.1.0"


def _host_devices() -> None:
    """One XLA host device per CPU core, set before JAX starts (``XLA_FLAGS``), so that a CPU
    render shards its rays over the cores (``render.devices: all``) the way it shards them over
    GPUs. Each device then runs whole chunks, where XLA's own threading inside one chunk's small
    operations gains little: with 16 chunks per call the cacti's cast at 1024x768 took 0.068 s
    on two devices and 0.103 s on one (``experiments/bench_scale_cpu_paths.yaml``, README).
    Nothing is changed when JAX is already
    imported, when ``XLA_FLAGS`` names a device count, or with ``JSKEL_HOST_DEVICES`` set (its
    value is the count; 1 keeps one device, as the tests do)."""
    import os
    import sys

    flags = os.environ.get("XLA_FLAGS", "")
    if "jax" in sys.modules or "xla_force_host_platform_device_count" in flags:
        return
    want = os.environ.get("JSKEL_HOST_DEVICES")
    if want:
        if not want.strip().isdigit() or int(want) < 1:
            raise ValueError(f"JSKEL_HOST_DEVICES: {want!r} is not a positive integer (XLA host devices to make)")
        n = int(want)
    else:
        try:
            n = len(os.sched_getaffinity(0))
        except AttributeError:  # not on Linux
            n = os.cpu_count() or 1
    if n > 1:
        os.environ["XLA_FLAGS"] = f"{flags} --xla_force_host_platform_device_count={n}".strip()


_host_devices()

from .config import ConfigError as ConfigError
from .config import load as load
from .interface import Built as Built
from .rays import Camera as Camera
from .rays import Hit as Hit
from .rays import Rays as Rays
from .rays import make_rays as make_rays
from .rays import map_chunks as map_chunks

__all__ = ["Built", "Camera", "ConfigError", "Hit", "Rays", "load", "make_rays", "map_chunks"]
