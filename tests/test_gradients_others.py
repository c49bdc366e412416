"""Derivatives of hit distances against finite differences in float64 (``test_gradients``'s
script and checks): the implicit tracers, the cell objects, the meshes, their fuzzed scales
and the fit's distance; a file of its own, so that the suite's two workers run it beside the
frusta's half."""

from __future__ import annotations

from test_gradients import EXPECTED, FRUSTA_HALF, run_checks


def test_hit_distances_of_the_other_representations_have_the_derivatives_finite_differences_give():
    others = [k for k in EXPECTED if k not in FRUSTA_HALF]
    assert others and run_checks(others) == {k: EXPECTED[k] for k in others}
