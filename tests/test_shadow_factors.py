"""The factor split of ``validation.shadow_factors`` (pure parts; the tool itself needs a
finished run and the shared assets)."""

from __future__ import annotations

import itertools
import math

import numpy as np

from validation.shadow_factors import FACTORS, irradiance, shapley


def test_shapley_is_exact_for_additive_gains_and_sums_to_the_total():
    gains = {"lights": 0.2, "receivers": 0.05, "occluders": 0.01}
    scores = {k: 0.6 + sum(g for g, on in zip(gains.values(), k, strict=True) if on)
              for k in itertools.product((False, True), repeat=3)}
    sh = shapley(scores)
    assert all(math.isclose(sh[f], gains[f]) for f in FACTORS), sh
    rng = np.random.default_rng(0)
    scores = {k: float(rng.random()) for k in itertools.product((False, True), repeat=3)}
    sh = shapley(scores)
    total = scores[(True, True, True)] - scores[(False, False, False)]
    assert math.isclose(sum(sh.values()), total, abs_tol=1e-12)
    # An interaction (a gain only when two factors are both swapped) is split evenly.
    scores = {k: float(k[0] and k[1]) for k in itertools.product((False, True), repeat=3)}
    sh = shapley(scores)
    assert math.isclose(sh["lights"], 0.5) and math.isclose(sh["receivers"], 0.5)
    assert sh["occluders"] == 0.0


def test_irradiance_matches_the_definition():
    class Rec:
        normals_np = [np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0]])]

    dirs = np.array([[0.0, 1.0, 0.0], [0.6, 0.8, 0.0]])
    vis = [np.array([[1.0, 0.0], [1.0, 1.0]])]
    out = irradiance(Rec(), vis, dirs, np.array([2.0, 1.0]), (1, 2))
    # pixel 0: 2 * 1 * 1 + 1 * 0.8 * 0; pixel 1: 2 * 0 + 1 * 0.6 * 1
    assert np.allclose(out, [[[2.0, 0.6]]])
