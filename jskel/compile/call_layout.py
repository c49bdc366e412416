"""Where the executor's calls put each ray on the host: a call's rays laid out for its devices,
and its outputs written straight into the result.

A call of ``map_chunks`` traces ``size`` rays: ``per_call`` chunks of ``chunk`` rays on each of
``devices`` devices. Chunk ``p`` of the call (in ray order) goes to device ``p % devices``,
slot ``p // devices``: in screen-tile order a contiguous run of the image may be mostly sky on
one device and mostly scene on the other, so the chunks are dealt out in turn and the call
waits for neither. With one device, or one chunk per call, that is plain ray order.

Only the chunks that hold rays are copied, in and out. A grouped call (``per_call > 1``) skips
its padding chunks (``executor.Grouped``), so they are left zero on the way in and never read
on the way out; each output is copied once, from each device's own buffer (on a CPU, a view of
it) into the result, with no gathered, re-ordered or concatenated copies between. A call of
one chunk per device traces every ray it holds, so its padding repeats the last ray, as a
batch smaller than one chunk is padded.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np


def pad_to(x, n: int):
    """``x`` (leading axis m <= n) padded to ``n`` rows by repeating its last row."""
    pad = n - x.shape[0]
    if pad == 0:
        return x
    xp = np if isinstance(x, np.ndarray) else jax.numpy
    filler = xp.broadcast_to(x[-1:], (pad,) + x.shape[1:])
    return xp.concatenate([x, filler], axis=0)


class Layout(NamedTuple):
    """A batch of ``n`` rays cut into calls of ``size`` rays: ``per_call`` chunks on each of
    ``devices`` devices."""

    n: int
    size: int
    per_call: int
    devices: int

    @property
    def chunk(self) -> int:
        """Rays per chunk."""
        return self.size // (self.per_call * self.devices)

    @property
    def calls(self) -> int:
        return -(-self.n // self.size)

    def live(self, i: int) -> int:
        """Chunks of call ``i`` that hold rays (the first ones in ray order)."""
        return -(-min(self.size, self.n - i * self.size) // self.chunk)

    def live_flags(self, i: int) -> np.ndarray:
        """(devices * per_call,) bool in the call's device order: which slots hold rays."""
        slot = np.arange(self.per_call)[None, :] * self.devices + np.arange(self.devices)[:, None]
        return (slot < self.live(i)).reshape(-1)


def call_rays(a: np.ndarray, lay: Layout, i: int) -> np.ndarray:
    """Call ``i``'s rows of the host array ``a`` (leading axis ``lay.n``) in the call's device
    order, ``lay.size`` rows. One chunk per device: padded by repeating the last ray (every
    ray is traced). Grouped: the chunks holding rays are copied, the last one's tail repeats
    the last ray, the padding chunks stay zero (never traced)."""
    lo = i * lay.size
    rows = a[lo : lo + lay.size]
    if lay.per_call == 1 or lay.devices == 1 and rows.shape[0] == lay.size:
        return pad_to(rows, lay.size)  # (the call's rays in order: a view when it is full)
    c, live, d = lay.chunk, lay.live(i), lay.devices
    out = aligned_zeros((lay.size,) + a.shape[1:], a.dtype)
    slots = out.reshape((d, lay.per_call, c) + a.shape[1:])
    if a.ndim and a.strides[0] == 0 and rows.shape[0]:
        # one row broadcast to every ray (a camera's origin, t_min): filled, not gathered
        # (NumPy's strided copy of a broadcast through the dealing was the slowest part of the layout)
        block = np.ascontiguousarray(np.broadcast_to(rows[0], (c,) + a.shape[1:]))
        for p in range(live):
            slots[p % d, p // d] = block
        return out
    whole = min(live, rows.shape[0] // c) // d  # slots full on every device
    if whole:
        slots[:, :whole] = np.swapaxes(rows[: whole * d * c].reshape((whole, d, c) + a.shape[1:]), 0, 1)
    for p in range(whole * d, live):
        slots[p % d, p // d] = pad_to(rows[p * c : (p + 1) * c], c)
    return out


ALIGN = 64


def aligned_zeros(shape: tuple, dtype) -> np.ndarray:
    """``np.zeros(shape, dtype)`` whose data starts on a 64-byte boundary. JAX's CPU client
    takes such a host array as a device buffer without copying it (it aliases it; NumPy's own
    allocations start on 16 bytes, and those it copies): a call's rays, laid out here once,
    are not copied again on the way in (``tests/scripts/host_path.py``, docs/choices.md#aligned-rays).
    The shards of a call start on chunk boundaries, multiples of 64 bytes for any chunk of 16
    rays or more, so each device's shard is aligned too. Zeros: a grouped call's padding
    chunks are left as they are (never written, never traced)."""
    dtype = np.dtype(dtype)
    n = int(np.prod(shape)) * dtype.itemsize
    raw = np.zeros(n + ALIGN, np.uint8)
    off = (-raw.ctypes.data) % ALIGN
    return raw[off : off + n].view(dtype).reshape(shape)


def output_buffers(out, lay: Layout):
    """Host arrays for every output of ``map_chunks`` (the first call's ``out`` gives their
    trailing shapes and dtypes), ``lay.calls * lay.size`` rows: :func:`write_call` fills the
    rows of the chunks holding rays, ``[:lay.n]`` is the result."""
    return jax.tree_util.tree_map(lambda x: np.empty((lay.calls * lay.size,) + x.shape[1:], x.dtype), out)


def _shards(x, per_device: int):
    """(device slot, host view of its rows) for each addressable shard of the output ``x``."""
    for s in x.addressable_shards:
        start = s.index[0].start if s.index else None
        yield (start or 0) // per_device, np.asarray(s.data)


def write_call(bufs, out, lay: Layout, i: int) -> None:
    """Copy call ``i``'s outputs (device arrays, in the call's device order) into ``bufs``
    (:func:`output_buffers`) in ray order: per device its chunks that hold rays, no more."""
    c, live, d, per = lay.chunk, lay.live(i), lay.devices, lay.per_call
    lo = i * lay.size

    def one(buf, x):
        slots = buf[lo : lo + lay.size].reshape((per, d, c) + buf.shape[1:])
        for dev, view in _shards(x, per * c):
            j = min(per, max(0, -(-(live - dev) // d)))
            if j:
                slots[:j, dev] = view.reshape((per, c) + buf.shape[1:])[:j]

    jax.tree_util.tree_map(one, bufs, out)
