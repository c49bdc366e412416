"""The executor's host layout of a call (``jskel.compile.call_layout``), against a reference written
here in NumPy: chunk p of a call goes to device p % D, slot p // D; a grouped call's padding
chunks are neither filled on the way in nor copied back on the way out (what a 1024x768
frame in 64-chunk calls over two devices used to pay for a third of its slots); a call of one
chunk per device repeats the last ray. No program is compiled here."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest

from jskel.compile.call_layout import Layout, call_rays, output_buffers, write_call

# (rays, rays per call, chunks per device per call, devices): full and partial last calls,
# a partial last chunk, devices with no live chunk, one device, one chunk per device
CASES = [(1200, 400, 4, 2), (850, 400, 4, 4), (977, 160, 8, 2), (5000, 4096, 16, 1), (700, 400, 1, 4), (61, 64, 1, 1)]


def _reference_call(a, n, size, per, dev, i):
    """Call i's rows in device order and which slots hold rays, written out chunk by chunk."""
    c = size // (per * dev)
    want = np.zeros((size,) + a.shape[1:], a.dtype)
    live = np.zeros(dev * per, bool)
    last = a[n - 1]
    for p in range(per * dev):
        lo = i * size + p * c
        rows = a[lo : min(lo + c, n)]
        at = ((p % dev) * per + p // dev) * c
        if len(rows):
            live[(p % dev) * per + p // dev] = True
            want[at : at + len(rows)] = rows
            want[at + len(rows) : at + c] = rows[-1]
        elif per == 1:  # every ray of a one-chunk call is traced: the padding repeats the last ray
            want[at : at + c] = last
    return want, live


@pytest.mark.parametrize("n, size, per, dev", CASES)
def test_call_rays_deal_chunks_to_devices_and_leave_grouped_padding_zero(n, size, per, dev):
    a = np.arange(n * 3, dtype=np.float32).reshape(n, 3) + 1.0
    lay = Layout(n, size, per, dev)
    assert lay.calls == -(-n // size)
    one = np.broadcast_to(a[3], a.shape)  # a camera's origin: one row broadcast to every ray
    for i in range(lay.calls):
        want, live = _reference_call(a, n, size, per, dev, i)
        np.testing.assert_array_equal(call_rays(a, lay, i), want, err_msg=f"call {i}")
        np.testing.assert_array_equal(lay.live_flags(i), live, err_msg=f"call {i}")
        want, _ = _reference_call(np.ascontiguousarray(one), n, size, per, dev, i)
        np.testing.assert_array_equal(call_rays(one, lay, i), want, err_msg=f"call {i}, broadcast rows")


def test_grouped_calls_start_every_device_shard_on_64_bytes():
    """JAX's CPU client aliases a host array whose data starts on 64 bytes instead of copying
    it: a grouped call's rays (origins (n, 3) and t (n,)) and each device's shard of them must
    start there, whatever NumPy's own allocation gives."""
    from jskel.compile.call_layout import aligned_zeros

    for shape, dtype in [((10, 3), np.float32), ((7,), np.float64), ((33, 2), np.int32)]:
        for _ in range(8):
            x = aligned_zeros(shape, dtype)
            assert x.shape == shape and x.dtype == dtype and x.flags.c_contiguous and x.ctypes.data % 64 == 0
    n, size, per, dev = 5000, 4096, 16, 2
    lay = Layout(n, size, per, dev)
    for a in (np.ones((n, 3), np.float32), np.ones((n,), np.float32)):
        for i in range(lay.calls):
            out = call_rays(a, lay, i)
            shard = out.reshape((dev, -1) + a.shape[1:])
            assert all(shard[d].ctypes.data % 64 == 0 for d in range(dev))


def _as_device_output(x, dev):
    """A stand-in for a call's output sharded over ``dev`` devices on its leading axis: its
    ``addressable_shards`` (index, data), as a jax Array gives them."""
    per = x.shape[0] // dev
    shards = [SimpleNamespace(index=(slice(d * per, (d + 1) * per),), data=x[d * per : (d + 1) * per]) for d in range(dev)]
    return SimpleNamespace(shape=x.shape, dtype=x.dtype, addressable_shards=shards)


@pytest.mark.parametrize("n, size, per, dev", CASES)
def test_outputs_come_back_in_ray_order_and_padding_chunks_are_not_copied(n, size, per, dev):
    values = np.arange(n, dtype=np.float64) * 2.0 + 1.0
    lay = Layout(n, size, per, dev)
    c = lay.chunk
    outs = [_as_device_output(_reference_call(values, n, size, per, dev, i)[0], dev) for i in range(lay.calls)]
    bufs = output_buffers(outs[0], lay)
    bufs[:] = np.nan
    for i, out in enumerate(outs):
        write_call(bufs, out, lay, i)
    np.testing.assert_array_equal(bufs[:n], values)
    written = -(-n // c) * c  # rows of the chunks holding rays; every row after them is padding
    assert np.all(np.isnan(bufs[written:])), f"{np.sum(~np.isnan(bufs[written:]))} padding rows copied"


def test_replicated_parameters_are_copied_once_for_the_same_arrays():
    """``executor.replicated``: the same tree of the same (immutable) JAX arrays over an equal
    mesh is placed once; new arrays, another tree structure or NumPy leaves (mutable) are
    placed anew, and what comes back always has the given structure and values."""
    import jax
    import jax.numpy as jnp

    from jskel.executor import replicated

    mesh = lambda: jax.sharding.Mesh(np.array(jax.devices()[:1]), ("rays",))  # noqa: E731 (a new, equal mesh each call)
    a, b = jnp.arange(6.0), jnp.ones((2, 3), jnp.int32)
    first = replicated({"a": a, "b": b}, mesh())
    assert replicated({"a": a, "b": b}, mesh()) is first
    np.testing.assert_array_equal(np.asarray(first["a"]), np.arange(6.0))
    fresh = replicated({"a": a + 1.0, "b": b}, mesh())
    assert fresh is not first
    np.testing.assert_array_equal(np.asarray(fresh["a"]), np.arange(6.0) + 1.0)
    other = replicated({"a": a, "c": b}, mesh())  # the same leaves under other keys
    assert set(other) == {"a", "c"}
    host = np.arange(3.0)
    one = replicated({"h": host}, mesh())
    host[0] = 7.0  # changed in place: must be seen by the next placement
    np.testing.assert_array_equal(np.asarray(replicated({"h": host}, mesh())["h"]), [7.0, 1.0, 2.0])
    np.testing.assert_array_equal(np.asarray(one["h"])[1:], [1.0, 2.0])
