"""Cook-Torrance BRDF of the decomposition (paper Eq. 3-5) as pure Dr.Jit functions.

f_r = (1 - m) a / pi + D F G / (4 (n . l)(n . v)) with
- D: GGX / Trowbridge-Reitz, alpha = roughness^2 (the Disney/UE4 remapping);
- F: Schlick, F0 = lerp(0.04, a, m) (dielectric 4 % for m = 0, the albedo for metals);
- G: the *separable* (uncorrelated) Smith form with the exact GGX G1,
  G1(x) = 2 x / (x + sqrt(alpha^2 + (1 - alpha^2) x^2)).

The specular term is evaluated as D F Vis with Vis = G / (4 (n . l)(n . v)) =
1 / ((nl + sqrt(a2 + (1 - a2) nl^2)) (nv + sqrt(a2 + (1 - a2) nv^2))), which stays finite at
grazing angles (n . l = 0 or n . v = 0): no 0 / 0. Roughness is clamped to ``ROUGHNESS_MIN``
(a mirror's delta lobe cannot be sampled by a 128-direction grid, and alpha = 0 makes D
infinite); n . l and n . v are clamped to [0, 1].

Every function returns the *cosine-weighted* BRDF f_r (n . l)^+ (what Eq. 17 sums), per
colour channel, so that a light below the horizon contributes exactly zero.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

ROUGHNESS_MIN = 0.04  # alpha >= 1.6e-3: D <= 1 / (pi alpha^2) ~ 1.2e5, finite in float32
F0_DIELECTRIC = 0.04
_H_EPS = 1e-12  # |l + v|^2 below this (l = -v): no half vector, the lobe is zero there


def _clamp_cos(x):
    return dr.clip(x, 0.0, 1.0)


def ggx_alpha(roughness):
    """GGX alpha = max(roughness, ROUGHNESS_MIN)^2. At the clamp itself the gradient is the
    one from above: stage 4 projects roughness onto [ROUGHNESS_MIN, 1] after each step, and
    ``dr.maximum`` would give a tie's gradient to the constant, so a surfel projected onto
    the clamp could never become rougher again."""
    return dr.square(dr.select(roughness >= ROUGHNESS_MIN, roughness, ROUGHNESS_MIN))


def ggx_d(n_dot_h, roughness, sin2_nh=None):
    """GGX normal distribution D(h) (normalised: int D (n . h) dw_h = 1).

    ``sin2_nh`` = |n x h|^2 when known: 1 - (n . h)^2 cancels catastrophically in float32
    near the peak of a sharp lobe (0.2 % error at the roughness clamp), the cross does not.
    """
    a = ggx_alpha(roughness)
    a2 = a * a
    c = _clamp_cos(n_dot_h)
    s2 = 1.0 - c * c if sin2_nh is None else dr.select(n_dot_h > 0.0, sin2_nh, 1.0)
    t = s2 + c * c * a2  # = 1 + (n . h)^2 (a2 - 1)
    return a2 / (math.pi * t * t)


def schlick_f(v_dot_h, f0):
    """Schlick's Fresnel: F0 + (1 - F0) (1 - v . h)^5 (``f0`` scalar or colour)."""
    x = 1.0 - _clamp_cos(v_dot_h)
    x2 = x * x
    return f0 + (1.0 - f0) * (x2 * x2 * x)


def smith_vis(n_dot_l, n_dot_v, roughness):
    """G / (4 (n . l)(n . v)) for the separable Smith G = G1(l) G1(v), finite at 0."""
    a = ggx_alpha(roughness)
    a2 = a * a
    nl, nv = _clamp_cos(n_dot_l), _clamp_cos(n_dot_v)
    gl = nl + dr.sqrt(a2 + (1.0 - a2) * nl * nl)
    gv = nv + dr.sqrt(a2 + (1.0 - a2) * nv * nv)
    return dr.rcp(gl * gv)


def diffuse(n, l, albedo, metallic):
    """(1 - m) a / pi (n . l)^+ : [P] colour. ``n``, ``l`` unit Vector3f."""
    nl = dr.maximum(dr.dot(n, l), 0.0)
    return albedo * ((1.0 - metallic) * nl / math.pi)


def specular(n, l, v, albedo, roughness, metallic):
    """D F G / (4 (n . l)(n . v)) (n . l)^+ : [P] colour. ``v`` points toward the viewer."""
    s = l + v
    s2 = dr.squared_norm(s)
    ok = s2 > _H_EPS
    h = s * dr.rsqrt(dr.select(ok, s2, 1.0))
    nl = dr.dot(n, l)
    nv = dr.dot(n, v)
    f0 = dr.lerp(mi.Color3f(F0_DIELECTRIC), albedo, metallic)
    d = ggx_d(dr.dot(n, h), roughness, dr.squared_norm(dr.cross(n, h)))
    f = schlick_f(dr.dot(v, h), f0)
    vis = smith_vis(nl, nv, roughness)
    w = dr.select(ok & (nl > 0.0), d * vis * nl, 0.0)
    return f * w


def cook_torrance(n, l, v, albedo, roughness, metallic, with_specular: bool = True):
    """f_r (n . l)^+ of the full model (diffuse + specular lobe): [P] Color3f.

    ``with_specular=False`` drops the lobe (a diffuse scene: no GGX work at all).
    """
    out = diffuse(n, l, albedo, metallic)
    if with_specular:
        out = out + specular(n, l, v, albedo, roughness, metallic)
    return out
