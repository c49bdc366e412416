"""jskel: ray casting skeletal and detail surface representations in JAX."""

from ._version import __version__ as __version__


from .config import ConfigError as ConfigError
from .config import load as load
from .compile.devices import use_host_devices as use_host_devices
from .compile.cache import use_compilation_cache as use_compilation_cache
from .interface import Built as Built
from .camera import Camera as Camera
from .rays import Hit as Hit
from .rays import Rays as Rays
from .rays import make_rays as make_rays
from .spawning import refine as refine
from .spawning import spawn as spawn
from .executor import map_chunks as map_chunks
from .view import view as view  # the function; the module stays importable as jskel.view

__all__ = ["Built", "Camera", "ConfigError", "Hit", "Rays", "load", "make_rays", "map_chunks", "refine", "spawn", "use_compilation_cache", "use_host_devices", "view"]
