"""Scenes of several objects and effects (issue 7), against float64 NumPy references.

Every geometric reference here is written in the test: planes, spheres (a lone metaball's
surface F = T is the sphere of radius R sqrt(1 - sqrt(T)) for f(r) = (1 - r^2/R^2)^2) and
vertical cylinders, intersected, reflected and refracted in float64.
"""

from __future__ import annotations

import copy

import jax
import numpy as np
import pytest

from jskel.config import ConfigError, validate
from jskel.render import render
from jskel.render._scene import Scene, build_scene, scene_call
from jskel.shading import encode_png, srgb_encode
from jskel.rays import make_rays

T = 0.5  # implicit threshold


def sphere_radius(R, thr=T):
    return R * np.sqrt(1.0 - np.sqrt(thr))


def run(raw):
    exp = validate(copy.deepcopy(raw))
    return exp, render(exp, progress=False)


def cylinder(x, z, r, h, **shape):
    """A closed vertical frusta cylinder from y = 0 to h at (x, z) (geometric normals)."""
    return {"type": "frusta", "skeleton": {"joints": [[x, 0, z], [x, h, z]], "radii": [r, r], "parents": [-1, 0]},
            "normals": "geometric", **shape}


def balls(*cr):
    return {"type": "implicit", "threshold": T, "balls": [{"center": list(c), "radius": r} for c, r in cr]}


def camera(eye, target, w, h, fov=40.0):
    return {"eye": list(eye), "target": list(target), "up": [0, 1, 0], "fov_deg": fov, "width": w, "height": h}


def camera_rays(cam):
    """Pixel-centre rays, row-major, float64 (the camera model written out again)."""
    eye, tgt = np.asarray(cam["eye"], float), np.asarray(cam["target"], float)
    f = (tgt - eye) / np.linalg.norm(tgt - eye)
    r = np.cross(f, [0, 1, 0])
    r /= np.linalg.norm(r)
    u = np.cross(r, f)
    w, h = cam["width"], cam["height"]
    th = np.tan(np.radians(cam["fov_deg"]) / 2)
    xs = ((np.arange(w) + 0.5) / w * 2 - 1) * th * w / h
    ys = (1 - (np.arange(h) + 0.5) / h * 2) * th
    px, py = np.meshgrid(xs, ys)
    d = f + px.reshape(-1, 1) * r + py.reshape(-1, 1) * u
    cos = 1.0 / np.linalg.norm(d, axis=1)
    return eye, d * cos[:, None], cos, (2 * th / h) ** 2


def hit_sphere(o, d, c, rs):
    """Nearest t > 0 of rays (o (N,3) or (3,), d (N,3) unit) on a sphere; inf on a miss; and the
    ray's closest distance to the centre."""
    oc = o - c
    b = np.sum(oc * d, axis=-1)
    q = np.sum(oc * oc, axis=-1) - b * b
    disc = rs * rs - q
    s = np.sqrt(np.maximum(disc, 0))
    t0, t1 = -b - s, -b + s
    t = np.where(t0 > 1e-9, t0, np.where(t1 > 1e-9, t1, np.inf))
    return np.where(disc >= 0, t, np.inf), np.where(b < 0, np.sqrt(np.maximum(q, 0)), np.inf)


def hit_cylinder(o, d, x, z, r, far=False):
    """Side hit of rays on the infinite vertical cylinder at (x, z): (t, point); near root (or
    far root, for rays inside)."""
    ex, ez = o[..., 0] - x, o[..., 2] - z
    a = d[:, 0] ** 2 + d[:, 2] ** 2
    b = ex * d[:, 0] + ez * d[:, 2]
    c = ex * ex + ez * ez - r * r
    disc = b * b - a * c
    s = np.sqrt(np.maximum(disc, 0))
    t = (-b + s) / a if far else (-b - s) / a
    t = np.where((disc > 0) & (t > 1e-9), t, np.inf)
    return t, o + np.where(np.isfinite(t), t, 0)[:, None] * d


def radial(p, x, z, r):
    n = np.stack([p[:, 0] - x, np.zeros(len(p)), p[:, 2] - z], axis=1)
    return n / r


# --------------------------------------------------------------------------- two objects


# block culling: these tests are about the scene's integrator, and a BVH's bins program compiles
# twice as long (scenes with a BVH object: test_mesh's mirror scene, the cacti scene experiments)
SAG = {"type": "frusta", "skeleton": {"procedural": "saguaro", "seed": 0, "scale": 0.5, "offset": [-1.8, -0.5, 0]}, "accel": "blocks"}
BLOB = balls(((1.4, 1.0, 0.0), 1.3), ((1.9, 1.6, 0.3), 0.9))
CAM2 = camera((0.0, 1.5, 7.0), (0.0, 1.0, 0.0), 96, 64)
NO_SHADOW = [{"direction": [0.4, 0.9, 0.5], "shadows": False}]


def test_two_objects_render_as_each_alone():
    _, both = run({"objects": [{"shape": SAG}, {"shape": BLOB}], "camera": CAM2, "lights": NO_SHADOW})
    alone = [run({"object": s, "camera": CAM2, "lights": NO_SHADOW})[1] for s in (SAG, BLOB)]
    obj = both.aovs["obj"]
    hit = [np.isfinite(a.hits.t) for a in alone]
    assert hit[0].sum() > 200 and hit[1].sum() > 200  # both objects are in view
    for k in (0, 1):
        only = hit[k] & ~hit[1 - k]  # where the objects do not overlap on screen
        assert np.array_equal(obj[only], np.full(only.sum(), k))
        a, b = alone[k].hits, both.hits
        # an identity transform hands the object the very floats a single-object render gives it
        np.testing.assert_array_equal(b.t[only], a.t[only])
        np.testing.assert_array_equal(b.prim[only], a.prim[only])
        # normals and uv within an ulp or two (XLA may fuse the two programs' arithmetic differently)
        np.testing.assert_allclose(b.normal[only], a.normal[only], rtol=0, atol=4e-7)
        np.testing.assert_allclose(b.uv[only], a.uv[only], rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(b.position[only], a.position[only], rtol=0, atol=1e-5)
    none = ~hit[0] & ~hit[1]
    assert np.all(obj[none] == -1) and np.all(~np.isfinite(both.hits.t[none]))


def test_a_single_object_shadows_itself_where_a_light_asks():
    """A single object is a scene of one: a light that sets ``shadows: true`` gives it shadow
    rays (two exact spheres in one implicit object, one in the other's shadow); the default
    light section gives none (no visibility output, no shadow code in the program)."""
    c0, c1 = np.array([0.0, 1.0, 1.0]), np.array([1.6, 1.0, -2.6])
    r0, r1 = sphere_radius(1.0), sphere_radius(1.4)
    L = (c1 - c0) / np.linalg.norm(c1 - c0) + np.array([0.0, 0.15, 0.0])
    L /= np.linalg.norm(L)
    cam = camera((3.0, 1.8, 0.6), (0.0, 1.0, 1.0), 96, 64, fov=30)
    shape = balls((c0, 1.0), (c1, 1.4))
    raw = {"object": shape, "camera": cam, "lights": [{"direction": L.tolist(), "shadows": True}]}
    _, res = run(raw)
    assert res.run["effects"]["shadows"] and res.aovs["visibility"].shape == (96 * 64, 1)

    # float64 reference: the first sphere's hits, shadowed where the ray to the light meets the second
    eye, d, _, _ = camera_rays(cam)
    t0, _ = hit_sphere(eye, d, c0, r0)
    t1, _ = hit_sphere(eye, d, c1, r1)
    on0 = np.isfinite(t0) & (t0 < t1)
    p = eye + np.where(on0, t0, 0.0)[:, None] * d
    lit_side = ((p - c0) / r0) @ L > 0
    t_sh, _ = hit_sphere(p, np.broadcast_to(L, p.shape), c1, r1)
    ref = on0 & lit_side & np.isfinite(t_sh)
    got = on0 & (res.aovs["visibility"][:, 0] == 0)
    assert ref.sum() > 400 and (on0 & ~ref).sum() > 400
    assert np.sum(got != ref) <= 0.03 * ref.sum()  # the shadow's rim, one pixel wide at most

    exp = validate(copy.deepcopy({**raw, "lights": [{"direction": L.tolist()}]}))  # the default: no shadow rays
    plain = render(exp, progress=False)
    assert plain.aovs is None and "effects" not in plain.run
    np.testing.assert_array_equal(plain.hits.t, res.hits.t)
    lit = on0 & ~ref & (res.aovs["visibility"][:, 0] == 1)
    np.testing.assert_allclose(plain.rgb[lit], res.rgb[lit], rtol=1e-6, atol=1e-7)
    assert np.all(plain.rgb[ref & got].sum(1) > res.rgb[ref & got].sum(1))  # shadowed pixels lose the light
    rays = make_rays(np.zeros((256, 3)), np.tile([0.0, 0.0, -1.0], (256, 1)))
    for r, scoped in ((raw, True), ({**raw, "lights": [{"direction": L.tolist()}]}, False)):
        exp = validate(copy.deepcopy(r))
        params, static, _, _, _ = build_scene(exp, np.float32)
        eqns = _eqns(jax.make_jaxpr(scene_call)(Scene(params, static), rays).jaxpr)
        assert any("shadow_rays" in str(e.source_info.name_stack) for e in eqns) == scoped
        assert not any(k in str(e.source_info.name_stack) for e in eqns for k in ("reflection_rays", "refraction_rays"))


def test_a_single_object_takes_jittered_samples_per_pixel():
    _, one = run({"object": BLOB, "camera": CAM2, "lights": NO_SHADOW})
    _, four = run({"object": BLOB, "camera": CAM2, "lights": NO_SHADOW, "render": {"spp": 4, "seed": 3}})
    np.testing.assert_array_equal(four.hits.t, one.hits.t)  # AOVs from the pixel-centre sample
    assert four.run["rays"] == 4 * one.run["rays"] and four.run["spp"] == 4
    hit = np.isfinite(one.hits.t).reshape(64, 96)
    pad = np.pad(hit, 1, mode="edge")
    flat = np.all([pad[1 + dy:65 + dy, 1 + dx:97 + dx] == hit for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0).reshape(-1)
    diff = np.abs(four.rgb - one.rgb).max(axis=1)
    # the background (constant) is exact wherever no sample meets the object; silhouettes blend
    np.testing.assert_array_equal(four.rgb[flat & ~hit.reshape(-1)], one.rgb[flat & ~hit.reshape(-1)])
    assert diff[~flat].mean() > 5 * diff[flat].mean()


# --------------------------------------------------------------------------- shadows


def test_shadow_area_of_a_blob_on_a_frusta_floor():
    R, c = 1.5, np.array([0.0, 1.5, 0.0])
    L = np.array([1.0, 0.8, 0.0])
    cam = camera((-4.0, 9.0, 4.0), (-1.5, 0.0, 0.0), 160, 120)  # from the shadow's side: the ball hides none of it
    floor = {"type": "frusta", "skeleton": {"joints": [[0, -0.5, 0], [0, 0, 0]], "radii": [20, 20], "parents": [-1, 0]}, "normals": "geometric"}
    _, res = run({"objects": [{"shape": floor}, {"shape": balls((c, R))}], "camera": cam,
                  "lights": [{"direction": L.tolist()}], "render": {"chunk": 4096}})
    got = (res.aovs["obj"] == 0) & (res.aovs["visibility"][:, 0] == 0)

    # float64 reference: the floor's top plane y = 0, the sphere F = T, the light's direction
    rs = sphere_radius(R)
    eye, d, cos, pix = camera_rays(cam)
    t_floor = np.where(d[:, 1] < 0, -eye[1] / d[:, 1], np.inf)
    t_ball, _ = hit_sphere(eye, d, c, rs)
    on_floor = np.isfinite(t_floor) & (t_floor < t_ball)
    p = eye + t_floor[:, None] * d
    lh = L / np.linalg.norm(L)
    t_sh, _ = hit_sphere(p, np.broadcast_to(lh, p.shape), c, rs)
    ref = on_floor & np.isfinite(t_sh)
    area = pix * cos**3 * t_floor**2 / np.abs(d[:, 1])  # each pixel's footprint on the floor
    a_ref, a_got = area[ref].sum(), area[got].sum()
    assert ref.sum() > 500
    # the measure itself: the shadow is an ellipse of area pi rs^2 / sin(elevation)
    assert abs(a_ref / (np.pi * rs**2 / lh[1]) - 1) < 0.02
    assert abs(a_got / a_ref - 1) < 0.01
    assert np.sum(got != ref) <= 0.01 * ref.sum()


# --------------------------------------------------------------------------- mirror and glass

MIRROR = (-1.3, -0.8, 0.7)  # x, z, r
GLASS = (1.3, 0.2, 0.6)
SPHERES = [((0.0, 1.0, 1.0), 1.0), ((1.6, 1.0, -2.6), 1.4)]  # far apart: two exact spheres
CAM3 = camera((0.0, 1.2, 7.0), (0.0, 1.0, 0.0), 160, 96, fov=36)
H3 = 2.4


def mirror_glass_scene(kr=1.0):
    return {
        "objects": [
            {"name": "mirror", "shape": cylinder(MIRROR[0], MIRROR[1], MIRROR[2], H3), "material": {"reflectivity": kr}},
            {"name": "glass", "shape": cylinder(GLASS[0], GLASS[1], GLASS[2], H3), "material": {"transparency": 1.0, "ior": 1.5}},
            {"name": "spheres", "shape": balls(*SPHERES)},
        ],
        "camera": CAM3,
        "lights": [{"direction": [0.3, 0.9, 0.5]}],
        "render": {"bounces": 3, "chunk": 4096},
    }


@pytest.fixture(scope="module")
def mirror_glass():
    return run(mirror_glass_scene())[1]


def _end_of_path(o, d, skip):
    """Which object a float64 ray (o, d) meets first among the spheres (2) and the cylinders
    other than ``skip``; -1 if none; and whether it passes near a sphere's silhouette."""
    best, who = np.full(len(o), np.inf), np.full(len(o), -1)
    near_edge = np.zeros(len(o), bool)
    for c, R in SPHERES:
        rs = sphere_radius(R)
        t, q = hit_sphere(o, d, np.asarray(c), rs)
        near_edge |= np.abs(q - rs) < 0.02 * rs
        better = t < best
        best, who = np.where(better, t, best), np.where(better, 2, who)
    for k, (x, z, r) in enumerate((MIRROR, GLASS)):
        if k == skip:
            continue
        t, p = hit_cylinder(o, d, x, z, r)
        t = np.where((p[:, 1] > 0) & (p[:, 1] < H3), t, np.inf)
        better = t < best
        best, who = np.where(better, t, best), np.where(better, 9, who)  # 9: excluded below
    return who, near_edge


def _side_hits(d_all, eye, cyl, obj_aov, k):
    x, z, r = cyl
    t, p = hit_cylinder(np.broadcast_to(eye, d_all.shape), d_all, x, z, r)
    n = radial(p, x, z, r)
    ok = (obj_aov == k) & np.isfinite(t) & (p[:, 1] > 0.05) & (p[:, 1] < H3 - 0.05)
    ok &= np.abs(np.sum(d_all * n, axis=1)) > 0.1  # not grazing
    return ok, t, p, n


def test_mirror_cylinder_shows_the_sphere_where_geometry_predicts(mirror_glass):
    eye, d, _, _ = camera_rays(CAM3)
    ok, t, p, n = _side_hits(d, eye, MIRROR, mirror_glass.aovs["obj"], 0)
    np.testing.assert_allclose(mirror_glass.hits.t[ok], t[ok], rtol=1e-5)
    r = d - 2 * np.sum(d * n, axis=1, keepdims=True) * n
    want, edge = _end_of_path(p, r, skip=0)
    use = ok & ~edge & (want != 9)
    got = mirror_glass.aovs["reflect_obj"]
    assert use.sum() > 300 and np.sum(want[use] == 2) > 40  # the sphere is seen in the mirror
    assert np.mean(got[use] == want[use]) > 0.995


def _refract(d, n, eta):
    cosi = -np.sum(d * n, axis=1)
    k = 1 - eta**2 * (1 - cosi**2)
    return eta * d + (eta * cosi - np.sqrt(np.maximum(k, 0)))[:, None] * n, k < 0


def test_glass_rod_shows_what_snell_predicts(mirror_glass):
    eye, d, _, _ = camera_rays(CAM3)
    x, z, r = GLASS
    ok, t, p, n = _side_hits(d, eye, GLASS, mirror_glass.aovs["obj"], 1)
    np.testing.assert_allclose(mirror_glass.hits.t[ok], t[ok], rtol=1e-5)
    d1, tir1 = _refract(d, n, 1 / 1.5)
    d1 /= np.linalg.norm(d1, axis=1, keepdims=True)
    t2, p2 = hit_cylinder(p, d1, x, z, r, far=True)
    n2 = radial(p2, x, z, r)
    d2, tir2 = _refract(d1, -n2, 1.5)
    d2 /= np.linalg.norm(d2, axis=1, keepdims=True)
    want, edge = _end_of_path(p2, d2, skip=1)
    use = ok & ~tir1 & ~tir2 & np.isfinite(t2) & (p2[:, 1] > 0.05) & (p2[:, 1] < H3 - 0.05) & ~edge & (want != 9)
    got = mirror_glass.aovs["refract_obj"]
    assert use.sum() > 300 and np.sum(want[use] == 2) > 50 and np.sum(want[use] == -1) > 50
    assert np.mean(got[use] == want[use]) > 0.995


# --------------------------------------------------------------------------- only what the scene calls for


def _program(raw, n=256):
    exp = validate(copy.deepcopy(raw))
    params, static, _, _, _ = build_scene(exp, np.float32)
    rays = make_rays(np.zeros((n, 3)), np.tile([0.0, 0.0, -1.0], (n, 1)))
    jaxpr = jax.make_jaxpr(scene_call)(Scene(params, static), rays)
    return static, jaxpr, jax.jit(scene_call).lower(Scene(params, static), rays)


def _eqns(jaxpr):
    """Every equation of a jaxpr, sub-jaxprs (loops, conds) included."""
    out = []
    for e in jaxpr.eqns:
        out.append(e)
        for v in e.params.values():
            for sub in v if isinstance(v, (list, tuple)) else [v]:
                inner = getattr(sub, "jaxpr", sub)
                if hasattr(inner, "eqns"):
                    out += _eqns(inner)
    return out


def test_no_reflective_material_compiles_no_reflection_work():
    two = {"objects": [{"shape": cylinder(0, 0, 0.5, 2), "material": {"reflectivity": 0.8}}, {"shape": cylinder(2, 0, 0.5, 2)}],
           "camera": CAM2, "lights": [{"direction": [0.3, 0.9, 0.5], "shadows": False}]}
    plain = copy.deepcopy(two)
    plain["objects"][0]["material"]["reflectivity"] = 0.0
    s_on, j_on, low_on = _program(two)
    s_off, j_off, low_off = _program(plain)
    assert s_on.effects.reflection and s_on.effects.bounces == 2
    assert not s_off.effects.reflection and s_off.effects.bounces == 0
    e_on, e_off = _eqns(j_on.jaxpr), _eqns(j_off.jaxpr)
    scoped = lambda es: [e for e in es if "reflection_rays" in str(e.source_info.name_stack)]  # noqa: E731
    assert len(scoped(e_on)) > 0 and len(scoped(e_off)) == 0
    assert len(e_off) < len(e_on)
    f_on, f_off = low_on.cost_analysis()["flops"], low_off.cost_analysis()["flops"]
    assert f_off < f_on


def test_a_scene_render_hands_each_program_to_xla_once():
    """Nothing compiled twice in a process: a scene of two cylinders and a blob with shadows, at a
    lane count no other test uses (a static key of its own), hands XLA each program it needs
    once by name (``jskel.compile.cache.program_counts``, counted around the render), and the same
    render again hands it none."""
    from jskel.compile.cache import count_programs, program_counts

    raw = {"objects": [{"shape": cylinder(-2, 0, 0.5, 2)}, {"shape": BLOB}, {"shape": cylinder(2, 0, 0.3, 3)}],
           "camera": CAM2, "lights": [{"direction": [0.3, 0.9, 0.5]}], "render": {"lanes": 96}}
    count_programs()

    def handed(raw):
        before = program_counts()["by_name"]
        run(raw)
        after = program_counts()["by_name"]
        return {k: n - before.get(k, [0])[0] for k, (n, _) in after.items() if n != before.get(k, [0])[0]}

    first = handed(raw)
    assert first and all(n == 1 for n in first.values()), first
    assert handed(raw) == {}


def test_objects_of_one_shape_are_traced_once():
    """Objects of one representation, options and param shapes share one traced copy of their
    hit code (``render._hits.groups``): a scene of three cylinders, the middle one an implicit
    blob, traces as few equations as one cylinder and one blob do (each cylinder alone, it held
    about one more cylinder's worth). That the grouped objects' hits are right is checked by the
    mirror and glass tests above (the two cylinders form one group)."""
    from jskel.render._hits import groups

    def scene(*shapes):
        return {"objects": [{"shape": s} for s in shapes], "camera": CAM2, "lights": NO_SHADOW}

    def size(*shapes):
        exp = validate(scene(*shapes))
        params, static, _, _, _ = build_scene(exp, np.float32)
        rays = make_rays(np.zeros((64, 3)), np.tile([0.0, 0.0, -1.0], (64, 1)))
        return groups(params, static), len(_eqns(jax.make_jaxpr(scene_call)(Scene(params, static), rays).jaxpr))

    g3, n3 = size(cylinder(-2, 0, 0.5, 2), BLOB, cylinder(2, 0, 0.3, 3), cylinder(0, -1, 0.4, 1))
    g1, n1 = size(cylinder(-2, 0, 0.5, 2), BLOB)
    assert g3 == [[0, 2, 3], [1]] and g1 == [[0], [1]]
    _, n_cyl = size(cylinder(-2, 0, 0.5, 2))
    _, n_blob = size(BLOB)
    per_cylinder = n1 - n_blob  # roughly what one more traced cylinder adds
    assert per_cylinder > 100 and n3 < n1 + 0.3 * per_cylinder, (n3, n1, n_cyl, n_blob)


def test_pixels_needing_no_secondary_ray_are_unchanged_by_the_effect(mirror_glass):
    _, plain = run(mirror_glass_scene(kr=0.0))  # the last reflective material removed
    on = mirror_glass
    assert not plain.run["effects"]["reflection"] and on.run["effects"]["reflection"]
    same = on.aovs["secondary"] == 0  # every pixel that needs no secondary ray
    assert np.array_equal(plain.aovs["obj"], on.aovs["obj"]) and same.sum() > 5000
    np.testing.assert_array_equal(plain.rgb[same], on.rgb[same])
    np.testing.assert_array_equal(plain.hits.t[same], on.hits.t[same])
    np.testing.assert_array_equal(plain.aovs["visibility"][same], on.aovs["visibility"][same])
    mirror = on.aovs["obj"] == 0
    assert mirror.sum() > 300 and np.mean(np.any(plain.rgb[mirror] != on.rgb[mirror], axis=1)) > 0.9
    # secondary rays only where a material calls for them (compaction, counted per pixel)
    assert np.all(on.aovs["secondary"][(on.aovs["obj"] == 2) | (on.aovs["obj"] == -1)] == 0)
    assert np.all(on.aovs["secondary"][mirror] >= 1)


def test_no_bounce_leaves_mirror_and_glass_black_and_the_rest_unchanged(mirror_glass):
    """``render.bounces = 0`` with both reflective and transparent materials: Whitted's sum keeps
    only ``(1 - kr - kt) * local``, which is 0 for the mirror (kr = 1) and the glass (kt = 1), and
    every pixel that needed no secondary ray is the bounced render's."""
    raw = mirror_glass_scene()
    raw["render"]["bounces"] = 0
    _, flat = run(raw)
    on = mirror_glass
    assert np.array_equal(flat.aovs["obj"], on.aovs["obj"])
    ends = (on.aovs["obj"] == 0) | (on.aovs["obj"] == 1)
    assert ends.sum() > 300 and np.all(flat.rgb[ends] == 0)
    same = on.aovs["secondary"] == 0
    assert same.sum() > 5000
    np.testing.assert_array_equal(flat.rgb[same], on.rgb[same])


# --------------------------------------------------------------------------- output, samples, validation


def test_srgb_transfer_matches_the_standard():
    x = np.array([0.0, 0.001, 0.0031308, 0.2, 0.5, 1.0])
    want = np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)
    np.testing.assert_allclose(srgb_encode(x), want, rtol=1e-12)
    assert encode_png(np.array([[[0.0, 0.5, 1.0]]]))[0, 0].tolist() == [0, 188, 255]
    assert encode_png(np.array([[[0.5, 0.5, 0.5]]]), gamma=2.2)[0, 0, 0] == int(0.5 ** (1 / 2.2) * 255 + 0.5)


def test_bad_scene_input_names_the_key():
    raw = {"objects": [{"shape": BLOB, "material": {"transparency": 0.5}}]}
    exp = validate(copy.deepcopy(raw))
    with pytest.raises(ValueError, match=r"objects\[0\]\.material\.transparency"):
        render(exp)
    bad = {"objects": [{"shape": {"type": "frusta", "skeleton": {"procedural": "saguaro", "sede": 1}},
                        "material": {"reflectivity": 0.7, "transparency": 0.6}}], "object": SAG}
    with pytest.raises(ConfigError) as e:
        validate(bad)
    text = str(e.value)
    assert "objects[0].shape.skeleton.sede: unknown key" in text
    assert "objects[0].material: reflectivity + transparency must not exceed 1" in text
    with pytest.raises(ConfigError, match="not both"):
        validate({"objects": [{"shape": SAG}], "object": SAG})
    with pytest.raises(ConfigError, match=r"lights\[0\]: a point light needs a 'position'"):
        validate({"objects": [{"shape": SAG}], "lights": [{"type": "point"}]})


# --------------------------------------------------------------------------- animation

BONES = {"type": "implicit", "threshold": T, "method": "lipschitz", "eps": 1e-3, "bones": [
    {"name": "upper", "head": [0, 0, 0], "tail": [0, 1.5, 0], "tube": [0.5, 0.5],
     "keys": [{"frame": 0, "rotate": [0, 0, 0]}, {"frame": 10, "rotate": [0, 0, 40]}]},
    {"name": "lower", "parent": "upper", "head": [0, 1.5, 0], "tail": [0, 3, 0], "tube": [0.5, 0.3],
     "keys": [{"frame": 0, "rotate": [0, 0, 0]}, {"frame": 10, "rotate": [50, 0, 0]}]}]}
CAM_A = camera((0.0, 1.5, 7.0), (0.0, 1.5, 0.0), 64, 48)


def test_scene_frame_poses_bones_as_the_object_frame_does():
    lights = [{"direction": [0.4, 0.9, 0.5], "shadows": False}]
    _, moved = run({"objects": [{"shape": BONES}], "frame": 7, "camera": CAM_A, "lights": lights})
    _, alone = run({"object": {**BONES, "frame": 7}, "camera": CAM_A, "lights": lights})
    _, rest = run({"objects": [{"shape": BONES}], "frame": 0, "camera": CAM_A, "lights": lights})
    np.testing.assert_array_equal(moved.hits.t, alone.hits.t)
    np.testing.assert_array_equal(moved.hits.prim, alone.hits.prim)
    assert np.sum(np.isfinite(moved.hits.t) != np.isfinite(rest.hits.t)) > 50  # the pose changed the picture


from test_implicit_anim import rot_xyz as _rot  # noqa: E402 - the Euler convention written out in a test


def test_rigid_motion_of_a_cell_object_equals_the_camera_moving_back(tmp_path):
    """A cell object moved by ``motion`` for 3 frames and scaled looks, from camera C, as the
    unmoved object looks from C carried back by the inverse of that rigid motion (depths scale by
    1/s): the motion, transform and camera-relative frames written out in float64 here."""
    cells_shape = {"type": "cells", "base": {"type": "torus", "major": 1.0, "minor": 0.45}, "tiles": 6,
                   "tile_map": {"type": "voronoi", "resolution": 16, "cells": 8, "seed": 0}, "cache": str(tmp_path / "cache")}
    lights = [{"direction": [0.4, 0.9, 0.5], "shadows": False}]
    s, f = 1.5, 3
    motion = {"translate": [0.2, 0.1, -0.3], "rotate_deg": [5.0, 12.0, 0.0]}
    cam = camera((0.3, 2.5, 5.5), (0.4, 0.2, -0.6), 64, 48)
    _, moved = run({"objects": [{"shape": cells_shape, "transform": {"scale": s, "translate": [0.1, 0, 0]}, "motion": motion}],
                    "frame": f, "camera": cam, "lights": lights})
    R = _rot(f * np.asarray(motion["rotate_deg"]))
    t = np.array([0.1, 0, 0]) + f * np.asarray(motion["translate"])
    back = lambda p: R.T @ (np.asarray(p) - t) / s  # noqa: E731 - world -> object
    cam0 = camera(back(cam["eye"]), back(cam["target"]), 64, 48)
    cam0["up"] = (R.T @ np.array([0.0, 1.0, 0.0])).tolist()
    _, still = run({"objects": [{"shape": cells_shape}], "camera": cam0, "lights": lights})
    a, b = moved.hits, still.hits
    both = np.isfinite(a.t) & np.isfinite(b.t)
    assert both.sum() > 300
    assert np.mean(np.isfinite(a.t) == np.isfinite(b.t)) > 0.995
    same = both & (a.prim == b.prim)
    assert np.mean(same[both]) > 0.99
    np.testing.assert_allclose(a.t[same] / s, b.t[same], rtol=2e-4)


def test_jittered_samples_are_seeded_and_keep_the_centre_aovs():
    base = {"objects": [{"shape": SAG}, {"shape": BLOB}], "camera": CAM2, "lights": NO_SHADOW}
    _, one = run(base)
    _, a = run({**base, "render": {"spp": 4, "seed": 3}})
    _, b = run({**base, "render": {"spp": 4, "seed": 3}})
    _, c = run({**base, "render": {"spp": 4, "seed": 4}})
    np.testing.assert_array_equal(a.rgb, b.rgb)  # deterministic for a seed
    assert np.any(a.rgb != c.rgb)
    np.testing.assert_array_equal(a.hits.t, one.hits.t)  # AOVs from the pixel-centre sample
    np.testing.assert_array_equal(a.aovs["obj"], one.aovs["obj"])
    # the mean of 4 samples differs from 1 sample only near silhouettes (where coverage is partial):
    # pixels whose 3x3 neighbourhood is one object in the single-sample render stay within shading change
    obj = one.aovs["obj"].reshape(64, 96)
    pad = np.pad(obj, 1, mode="edge")
    flat = np.all([pad[1 + dy:65 + dy, 1 + dx:97 + dx] == obj for dy in (-1, 0, 1) for dx in (-1, 0, 1)], axis=0).reshape(-1)
    edge = ~flat
    diff = np.abs(a.rgb - one.rgb).max(axis=1)
    assert diff[edge].mean() > 5 * diff[flat].mean()
    assert a.run["rays"] == 4 * one.run["rays"]


def test_cli_renders_a_scene_and_rejects_a_bad_one(tmp_path, capsys):
    import yaml

    from jskel.cli import main

    good = tmp_path / "scene.yaml"
    good.write_text(yaml.safe_dump({"objects": [{"shape": SAG}, {"shape": BLOB}], "camera": CAM2, "lights": NO_SHADOW}))
    assert main(["render", str(good), "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    obj = np.load(tmp_path / "out" / "obj.npy")
    vis = np.load(tmp_path / "out" / "visibility.npy")
    assert obj.shape == (64, 96) and vis.shape == (64, 96, 1) and set(np.unique(obj)) == {-1, 0, 1}
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump({"objects": [{"shape": BLOB, "material": {"transparency": 0.5}}], "camera": CAM2}))
    assert main(["render", str(bad), "--out", str(tmp_path / "bad")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "objects[0].material.transparency: 0.5" in err[0]
