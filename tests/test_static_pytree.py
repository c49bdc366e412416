"""Static data in the pytree (STYLE.md item 4): ``interface.Object`` carries a build's static
options as aux data, so the module-level queries are jitted once and cached by tree structure.

A frusta cylinder (one segment of equal radii, axis y from 0 to 2, radius 0.5) gives closed-form
hits; the cache checks count JAX's own executables and the executor's compile seconds.
"""

from __future__ import annotations

import jax
import numpy as np

from conftest import CHUNK, build_skeleton, frusta_object
from jskel import interface
from jskel.executor import map_chunks
from jskel.rays import make_rays

_INTERSECT = jax.jit(interface.intersect_each)  # one jitted function for every static setting


def _cylinder(radius=0.5):
    return build_skeleton([[0.0, 0.0, 0.0], [0.0, 2.0, 0.0]], [radius, radius], [-1, 0])


def _rays(built, n=CHUNK):
    """n rays along -z at heights y in (0.2, 1.8) and x in (-0.8, 0.8); those with |x| < r hit
    the cylinder's side at z = sqrt(r^2 - x^2), i.e. t = 5 - sqrt(r^2 - x^2) from z = 5."""
    rng = np.random.default_rng(3)
    x = rng.uniform(-0.8, 0.8, n)
    y = rng.uniform(0.2, 1.8, n)
    O = np.stack([x, y, np.full(n, 5.0)], axis=1)
    D = np.tile([0.0, 0.0, -1.0], (n, 1))
    return x, make_rays(O - built.anchor, D)


def _truth(x, r):
    inside = np.abs(x) < r
    return inside, 5.0 - np.sqrt(np.where(inside, r * r - x * x, 0.0))


def test_the_static_part_is_aux_data_and_the_params_are_the_leaves():
    b = _cylinder()
    obj = frusta_object(b)
    leaves, tree = jax.tree_util.tree_flatten(obj)
    assert len(leaves) == len(jax.tree_util.tree_leaves(b.params))
    assert all(a is c for a, c in zip(leaves, jax.tree_util.tree_leaves(b.params)))
    back = jax.tree_util.tree_unflatten(tree, leaves)
    assert back.static == b.static and back.rep == "frusta"
    other = interface.Object(b.params, b.static._replace(group=b.static.group // 2), "frusta")
    assert jax.tree_util.tree_structure(other) != tree
    assert jax.tree_util.tree_structure(frusta_object(_cylinder(0.4))) == tree  # new values, same structure


def test_new_values_compile_nothing_and_a_changed_static_compiles_once_more():
    b1, b2 = _cylinder(0.5), _cylinder(0.4)
    x, rays = _rays(b1)
    h1 = _INTERSECT(frusta_object(b1), rays)
    first = _INTERSECT._cache_size()
    h2 = _INTERSECT(frusta_object(b2), _rays(b2)[1])
    assert _INTERSECT._cache_size() == first
    changed = interface.Object(b1.params, b1.static._replace(group=b1.static.group // 2), "frusta")
    h3 = _INTERSECT(changed, rays)
    assert _INTERSECT._cache_size() == first + 1
    _INTERSECT(changed, _rays(b2)[1])
    assert _INTERSECT._cache_size() == first + 1
    for h, r in ((h1, 0.5), (h2, 0.4), (h3, 0.5)):  # every program gives the closed form
        hit, t = _truth(x, r)
        t_got = np.asarray(h.t, np.float64)
        np.testing.assert_array_equal(np.isfinite(t_got), hit)
        np.testing.assert_allclose(t_got[hit], t[hit], atol=2e-5)


def test_the_executor_reuses_the_module_level_function_per_static():
    b1, b2 = _cylinder(0.5), _cylinder(0.4)
    x, rays = _rays(b1)
    map_chunks(interface.intersect_each, frusta_object(b1), rays, chunk=CHUNK, progress=False)
    again = map_chunks(interface.intersect_each, frusta_object(b2), rays, chunk=CHUNK, progress=False)
    assert again.compile_s == 0.0
    changed = interface.Object(b1.params, b1.static._replace(group=b1.static.group // 4), "frusta")
    assert map_chunks(interface.intersect_each, changed, rays, chunk=CHUNK, progress=False).compile_s > 0.0
    hit, t = _truth(x, 0.4)
    np.testing.assert_allclose(np.asarray(again.out.t, np.float64)[hit], t[hit], atol=2e-5)


def test_occluded_and_the_two_stages_dispatch_through_the_object():
    b = _cylinder()
    x, rays = _rays(b)
    obj = frusta_object(b)
    occ, (t, prim) = jax.jit(lambda o, r: (interface.occluded(o, r), interface.cast_t_prim(o, r)))(obj, rays)
    hit, want = _truth(x, 0.5)
    np.testing.assert_array_equal(np.asarray(occ), hit)
    np.testing.assert_allclose(np.asarray(t, np.float64)[hit], want[hit], atol=2e-5)
    assert np.all(np.asarray(prim)[hit] == 0) and np.all(np.asarray(prim)[~hit] == -1)


def test_a_scene_of_one_reuses_its_program_for_new_values_and_keys_on_its_static():
    """``render._scene.Scene``: the scene's static part is aux data too, so the integrator's one
    module-level batch function (``scene_call``) compiles nothing for a second build of the same
    shapes, and gives that build's closed-form hits."""
    from jskel.config import validate
    from jskel.render._build import place_objects
    from jskel.render._scene import Scene, build_scene, scene_call

    def built(radius):
        raw = {"object": {"type": "frusta", "skeleton": {"joints": [[0, 0, 0], [0, 2, 0]], "radii": [radius, radius], "parents": [-1, 0]}},
               "camera": {"eye": [0, 1, 5], "target": [0, 1, 0], "up": [0, 1, 0], "fov_deg": 40, "width": 8, "height": 8}}
        exp = validate(raw)
        placed = place_objects(exp, np.float32)
        params, static, _, _, _ = build_scene(exp, np.float32, placed)
        return Scene(params, static), placed[0].built

    s1, b1 = built(0.5)
    s2, b2 = built(0.4)
    assert jax.tree_util.tree_structure(s1) == jax.tree_util.tree_structure(s2)
    lanes = s1.static._replace(lanes=s1.static.lanes // 2)
    assert jax.tree_util.tree_structure(Scene(s1.params, lanes)) != jax.tree_util.tree_structure(s1)
    x, rays = _rays(b1, 1024)
    map_chunks(scene_call, s1, rays, chunk=1024, progress=False)
    again = map_chunks(scene_call, s2, rays, chunk=1024, progress=False)
    assert again.compile_s == 0.0
    hit, t = _truth(x, 0.4)
    got = np.asarray(again.out["hit"].t, np.float64)
    np.testing.assert_array_equal(np.isfinite(got), hit)
    np.testing.assert_allclose(got[hit], t[hit], atol=2e-5)


def test_a_program_compiles_with_the_cpu_options_its_representations_agree_on(monkeypatch):
    """``Representation.cpu_compiler_options`` reach XLA through the executor: an object's own,
    a scene's the union of its objects' except a key they set differently (XLA's default then);
    the call that compiles passes them (recorded here instead of compiling)."""
    from jskel import executor, registry
    from jskel.render._scene import Scene

    frusta, implicit = registry.get("frusta"), registry.get("implicit")
    no_ynn = {"xla_cpu_experimental_ynn_fusion_type": ""}
    elemental = {"xla_cpu_use_fusion_emitters": False, **no_ynn}
    assert frusta.cpu_compiler_options == elemental and implicit.cpu_compiler_options == {}
    b = _cylinder()
    obj = frusta_object(b)
    assert executor.compiler_options((obj, None)) == elemental
    assert interface.agreed_options(["implicit", "frusta", "implicit"], [None] * 3) == elemental
    # the exact relief tracer asks for the fusion emitters: alone it has them, beside plain frusta neither wins
    from jskel.frusta import ReliefQuality

    exact = obj.static._replace(relief=ReliefQuality(method="exact"))
    assert interface.agreed_options(["frusta"], [exact]) == {"xla_cpu_use_fusion_emitters": True}
    assert interface.agreed_options(["frusta", "frusta"], [exact, obj.static]) == no_ynn
    monkeypatch.setattr(type(implicit), "cpu_compiler_options", {"xla_cpu_use_fusion_emitters": True, "xla_cpu_enable_fast_math": False})
    assert interface.agreed_options(["frusta", "implicit"], [None, None]) == {"xla_cpu_enable_fast_math": False, **no_ynn}
    scene = Scene(None, type("Static", (), {"reps": ("frusta", "implicit", "frusta"), "statics": (None, None, None)})())
    assert executor.compiler_options((scene, None)) == {"xla_cpu_enable_fast_math": False, **no_ynn}
    seen = []

    class Recorded(Exception):
        pass

    def compile_(self, compiler_options=None):
        seen.append(compiler_options)
        raise Recorded

    monkeypatch.setattr(jax.stages.Lowered, "compile", compile_)
    x, rays = _rays(b)
    fresh = interface.Object(b.params, b.static._replace(group=b.static.group // 8), "frusta")  # a static no test compiled
    try:
        map_chunks(interface.intersect_each, fresh, rays, chunk=CHUNK, progress=False)
    except Recorded:
        pass
    assert seen == [elemental]
