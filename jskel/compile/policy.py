"""jskel's one cache policy: where every cache lives (jskel's cache directory, switched off by
``JSKEL_CACHE=off``), and which directories a process may use (made with mode 0700; refused,
with one warning line, where another user owns them or group or others may write them)."""

from __future__ import annotations

import os
import stat
import sys
from pathlib import Path


def default_cache_dir(env=None) -> Path | None:
    """The cache directory the environment asks for: None with ``JSKEL_CACHE=off``, else
    ``JSKEL_CACHE_DIR``, ``$XDG_CACHE_HOME/jskel/jax`` or ``~/.cache/jskel/jax``. A value of
    ``JSKEL_CACHE`` other than on/off is a ``ValueError``."""
    env = os.environ if env is None else env
    switch = env.get("JSKEL_CACHE", "on").strip().lower()
    if switch not in ("on", "off", "1", "0", "true", "false", ""):
        raise ValueError(f"JSKEL_CACHE: {env['JSKEL_CACHE']!r} is not on or off")
    if switch in ("off", "0", "false"):
        return None
    if env.get("JSKEL_CACHE_DIR"):
        return Path(env["JSKEL_CACHE_DIR"]).expanduser()
    base = env.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "jskel" / "jax"


def data_dir(name: str, env=None) -> Path | None:
    """The folder ``name`` of jskel's cache directory (:func:`default_cache_dir`), where
    precomputed data are kept beside the compiled programs: ``~/.cache/jskel/jax/<name>``, or
    under ``JSKEL_CACHE_DIR``; None with ``JSKEL_CACHE=off``. Not created here."""
    root = default_cache_dir(env)
    return None if root is None else root / name


def unsafe_reason(path: Path) -> str | None:
    """Why ``path`` (an existing directory) must not hold executables this process loads: not
    a directory, owned by another user, or writable by group or others; None when it is safe."""
    st = path.stat()
    if not stat.S_ISDIR(st.st_mode):
        return "is not a directory"
    if os.name == "posix" and st.st_uid != os.getuid():
        return f"is owned by uid {st.st_uid}, not this user"
    if st.st_mode & (stat.S_IWGRP | stat.S_IWOTH):
        return f"is writable by group or others (mode {stat.S_IMODE(st.st_mode):o}; fix: chmod 700 {path})"
    return None


def _warn(line: str) -> None:
    print(f"jskel: warning: {line}", file=sys.stderr)


def prepared_dir(path: Path, what: str = "compilation cache") -> Path | None:
    """``path`` created with mode 0700 (its parents as the umask makes them), or None with one
    warning line (naming it as ``what``) when it cannot be made or is unsafe
    (:func:`unsafe_reason`); never raises. Every folder of jskel's cache directory goes through it."""
    try:
        path.mkdir(mode=0o700, parents=True, exist_ok=True)
        why = unsafe_reason(path)
    except OSError as e:
        _warn(f"{what} {path} cannot be used ({e.strerror or e}); running without it")
        return None
    if why is not None:
        _warn(f"{what} {path} {why}; running without it")
        return None
    return path
