"""Values that turn bad under jit are reported (issue 29, class 4): ``interface.checked_intersect``
for every representation and the frusta device rebuild's ``checked``, through ``checkify``. Each
bad value is set in the traced arrays themselves (a NaN ray origin, a NaN radius, a negative
radius, an infinite vertex, a zero step), so no host validation could have seen it; the line
each gives is written out here from the value set and its index. The unchecked entry points
hold none of it (their jaxpr is the representation's own batch)."""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import test_conformance as conformance
from jskel import registry
from jskel.config import ConfigError
from jskel.interface import Object, _checked_jit, checked_intersect, intersect

N = conformance.N


@pytest.fixture(scope="module")
def examples(tmp_path_factory):
    return conformance._examples(tmp_path_factory.mktemp("checked"))


@pytest.fixture(params=registry.names())
def case(request, examples):
    """The conformance suite's build of each representation (shared when both files run)."""
    if request.param not in conformance._CASES:
        conformance._CASES[request.param] = conformance.Case(request.param, examples[request.param])
    return conformance._CASES[request.param]


def _g(v) -> str:
    return f"{float(v):.6g}"


def _bad_params(name, params):
    """(params with one traced entry made bad, the line it gives), per representation, the
    entry chosen by the user's index (skeleton segment id, config primitive index)."""
    if name == "frusta":  # segment 3's base radius NaN
        f = params.plain.frusta
        row = int(np.nonzero(np.asarray(f.sid) == 3)[0][0])
        bad = params._replace(plain=params.plain._replace(frusta=f._replace(r1=f.r1.at[row].set(jnp.nan))))
        return bad, f"segments.r1[3]: not finite (got nan); 1 of {f.r1.shape[0]} entries"
    if name == "implicit":  # the config's primitive 1 (the second ball) of radius -0.5
        p = params.prims
        row = int(np.nonzero(np.asarray(params.prim_id) == 1)[0][0])
        bad = params._replace(prims=p._replace(ra=p.ra.at[row].set(-0.5)))
        return bad, f"primitives.ra[1]: negative (got -0.5); 1 of {p.ra.shape[0]} entries"
    if name == "mesh":  # triangle 7's second vertex at infinity in x
        v = np.asarray(params.v1[7])
        bad = params._replace(v1=params.v1.at[7, 0].set(jnp.inf))
        return bad, f"triangles.v1[7]: not finite (got [inf, {_g(v[1])}, {_g(v[2])}]); 1 of {params.v1.shape[0]} entries"
    assert name == "cells"  # a search step of 0
    return params._replace(step=jnp.zeros_like(params.step)), "step[0]: not positive (got 0); 1 of 1 entries"


def test_checked_intersect_names_the_bad_traced_value(case):
    obj = Object.of(case.rep, case.built)
    hit = checked_intersect(obj, case.rays)  # good values: the hits, nothing raised
    compiled = _checked_jit._cache_size()
    np.testing.assert_array_equal(np.isfinite(np.asarray(hit.t)), np.isfinite(case.batch.t))
    np.testing.assert_allclose(np.asarray(hit.t)[np.isfinite(case.batch.t)], case.batch.t[np.isfinite(case.batch.t)], rtol=1e-5)
    o = np.asarray(case.rays.origins).copy()
    o[5, 1] = np.nan
    with pytest.raises(ConfigError) as e:  # a ray (same shapes: no compile)
        checked_intersect(obj, case.rays._replace(origins=jnp.asarray(o)))
    assert e.value.lines == [f"rays.origins[5]: not finite (got [{_g(o[5, 0])}, nan, {_g(o[5, 2])}]); 1 of {N} entries"]
    params, line = _bad_params(case.name, case.built.params)
    with pytest.raises(ValueError) as e:
        checked_intersect(Object(params, case.built.static, case.name), case.rays)
    assert e.value.lines == [line]
    assert _checked_jit._cache_size() == compiled  # new values, the same program


def test_the_unchecked_intersect_is_the_representations_batch_alone(case):
    """``interface.intersect`` traces to exactly the jaxpr of the representation's own batch: the
    checks live in ``checked_intersect``'s program only."""
    obj = Object.of(case.rep, case.built)
    plain = jax.make_jaxpr(intersect)(obj, case.rays)
    own = jax.make_jaxpr(lambda p, r: case.rep.intersect_batch(p, case.built.static, r))(case.built.params, case.rays)
    assert str(plain) == str(own)
