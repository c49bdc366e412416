"""Reflection and refraction at a surface: the helpers the integrator traces secondary rays
with, public so that what a renderer's optics give can be tested against closed forms.

Every function takes batches: directions and normals (..., 3), scalars (...) broadcast
against them. ``reflect`` is the law of reflection; ``refract`` Snell's law (Nürnberg 2011,
Sec. 3.2.4: n1 sin(theta1) = n2 sin(theta2)) in vector form (as pbrt-v4's ``Refract``,
Sec. 9.3), returning where total internal reflection happens (sin(theta2) > 1:
no transmitted ray; the mirrored one instead) as a per-ray mask; ``refract_surface`` refracts
through a surface between outside (index 1) and an object of index ``ior`` from either side,
as the integrator does at every transparent hit. The integrator marks a pixel whose refracted
ray underwent total internal reflection with the ``jskel.rays.FLAG_TIR`` bit of its flags.
"""

from __future__ import annotations

import jax.numpy as jnp

from .numerics import safe_normalize, safe_sqrt


def reflect(d, n):
    """``d`` mirrored about the unit normal ``n``: ``d - 2 (d . n) n`` (the law of reflection:
    the component along ``n`` flips, the tangential one stays, so ``|r| = |d|``)."""
    return d - 2.0 * jnp.sum(d * n, axis=-1, keepdims=True) * n


def refract(d, n, eta):
    """Snell's law for a unit direction ``d`` meeting a unit normal ``n`` that faces against
    it (``n . d <= 0``), ``eta = n1 / n2`` (the index on ``d``'s side over the far side's).

    Returns ``(direction, tir)``: with ``cos_i = -d . n`` and ``k = 1 - eta^2 (1 - cos_i^2)``
    (``cos^2`` of the refraction angle), the unit direction ``eta d + (eta cos_i - sqrt(k)) n``
    where ``k >= 0``; where ``k < 0`` (``eta sin_i > 1``, beyond the critical angle) the
    mirrored direction ``reflect(d, n)``, and ``tir`` (...) True there. Values and
    derivatives stay finite at ``k = 0`` (``safe_sqrt``)."""
    eta = jnp.asarray(eta, d.dtype)
    cos_i = -jnp.sum(d * n, axis=-1)
    k = 1.0 - eta * eta * (1.0 - cos_i * cos_i)
    tir = k < 0
    t = eta[..., None] * d + (eta * cos_i - safe_sqrt(k))[..., None] * n
    return jnp.where(tir[..., None], reflect(d, n), t), tir


def refract_surface(d, n_out, ior):
    """The refracted direction through a surface of outward unit normal ``n_out`` between
    outside (index 1) and inside (index ``ior``), for a ray ``d`` (any length) from either
    side: entering (``d . n_out < 0``) with ``eta = 1 / ior`` about ``n_out``, leaving with
    ``eta = ior`` about ``-n_out``. Returns ``(unit direction, tir)`` as :func:`refract`
    (total internal reflection is possible on the way out only)."""
    d = safe_normalize(d)
    entering = jnp.sum(d * n_out, axis=-1) < 0
    nf = jnp.where(entering[..., None], n_out, -n_out)
    t, tir = refract(d, nf, jnp.where(entering, 1.0 / ior, ior))
    return jnp.where(tir[..., None], t, safe_normalize(t)), tir
