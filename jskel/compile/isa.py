"""The vector instruction set XLA's CPU backend compiles for: the widest the CPU has, unless
``XLA_FLAGS`` caps it with ``--xla_cpu_max_isa`` (which the benchmarks use to time a CPU without
AVX-512 on one that has it: ``isa:`` in a bench file).

XLA:CPU's LLVM backend targets the host CPU's features; ``--xla_cpu_max_isa=AVX2`` keeps it from
emitting anything newer (XLA's ``xla_cpu_max_isa`` flag, values ``SSE4_2``, ``AVX``, ``AVX2``,
``AVX512``, ...). A traversal's best packet, lane and candidate sizes can differ between a
16-lane and an 8-lane float32 vector unit, so the benchmarks record the ISA of every row
(:func:`xla_isa`), and a stored executable's key holds the CPU's own (:func:`cpu_isa`): one
compiled for AVX-512 is never loaded on a CPU without it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

#: the ISAs named here, narrowest first (XLA's names)
ISAS = ("SSE4_2", "AVX", "AVX2", "AVX512")

_FLAG = re.compile(r"--xla_cpu_max_isa=(\S+)")


def cpu_isa(cpuinfo: str | None = None) -> str:
    """The widest of :data:`ISAS` this CPU has, from the ``flags`` line of ``/proc/cpuinfo``
    (``cpuinfo``: that file's text; ``""`` where it cannot be read, e.g. not on Linux)."""
    if cpuinfo is None:
        try:
            cpuinfo = Path("/proc/cpuinfo").read_text(errors="replace")
        except OSError:
            return ""
    flags = set(next((ln.split(":", 1)[1].split() for ln in cpuinfo.splitlines() if ln.startswith("flags")), []))
    for isa, flag in (("AVX512", "avx512f"), ("AVX2", "avx2"), ("AVX", "avx"), ("SSE4_2", "sse4_2")):
        if flag in flags:
            return isa
    return ""


def max_isa_flag(xla_flags: str | None = None) -> str | None:
    """The ISA ``--xla_cpu_max_isa`` names in ``xla_flags`` (default: ``$XLA_FLAGS``), upper
    case, or None where it is not set (the last one given wins, as XLA parses them)."""
    found = _FLAG.findall(os.environ.get("XLA_FLAGS", "") if xla_flags is None else xla_flags)
    return found[-1].upper() if found else None


def xla_isa(xla_flags: str | None = None, cpuinfo: str | None = None) -> str:
    """The ISA XLA compiles this process's CPU programs for: the CPU's own (:func:`cpu_isa`),
    capped by ``--xla_cpu_max_isa`` where that names a narrower one of :data:`ISAS`."""
    own, cap = cpu_isa(cpuinfo), max_isa_flag(xla_flags)
    if cap not in ISAS:  # unset, or one of XLA's names above AVX512 (AVX512_VNNI, AMX, ...): no narrower cap
        return own
    if own not in ISAS:  # the CPU's features unknown: as XLA was told
        return cap
    return ISAS[min(ISAS.index(cap), ISAS.index(own))]


def with_max_isa(isa: str, xla_flags: str | None = None) -> str:
    """``XLA_FLAGS`` (default: ``$XLA_FLAGS``) with every ``--xla_cpu_max_isa`` removed and, for
    an ``isa`` other than ``default``, ``--xla_cpu_max_isa=isa`` added: what a process started
    to compile for ``isa`` gets."""
    rest = _FLAG.sub("", os.environ.get("XLA_FLAGS", "") if xla_flags is None else xla_flags).split()
    if isa != "default":
        rest.append(f"--xla_cpu_max_isa={isa}")
    return " ".join(rest)
