"""Fuzzing the rasterizer: no NaN/Inf in any image, AOV or gradient, whatever the surfels.

``hypothesis`` draws surfel sets and cameras in a scene of size ~1 (centres in [-1, 1]^3):

- standard deviations log-uniform from 1e-6 to 1e3 of the scene, each axis on its own;
- quaternions of any direction, axis-aligned, exactly zero (a degenerate one the loader
  refuses but an optimiser can reach), near zero (|q| from 1e-12, the smallest the loader
  accepts, to 1e-3) or large (|q| up to 1e6);
- opacities from logits in [-8, 8], alpha within 1e-7 .. 1e-2 of 1, and saturated logits;
- cameras outside the object, inside it, grazing a surfel's plane (the view ray within
  1e-7 .. 0.1 of it) and far away with a narrow field of view (a shadow map), perspective or
  orthographic, at 16 .. 32 pixels a side.

Each case is rendered with every AOV of ``raster.AOV_CHANNELS`` and a colour channel, and a
loss over all outputs is differentiated (``dr.backward``) with respect to positions,
log-scales, rotations, opacity logits and colours. A case fails when an output or a
gradient holds NaN/Inf, when alpha leaves [0, 1], or when rendering raises. On a failure
hypothesis shrinks it and the minimal failing example is printed::

    python -m validation.fuzz --cases 1000 [--seed 0]
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import sys
import time

import numpy as np
from hypothesis import HealthCheck, Phase, given, seed, settings
from hypothesis import strategies as st

import mi_shadowgs  # noqa: F401  (finds libLLVM before drjit loads)

SIZES = (16, 24, 32)
ALPHA_TOL = 1e-6  # float32 sums of weights that add up to <= 1


@dataclasses.dataclass(frozen=True)
class FuzzCase:
    """One fuzz input; plain tuples so that hypothesis prints it as a reproducible value."""

    position: tuple  # N x (x, y, z)
    log_scale: tuple  # N x (ln s_u, ln s_v)
    rotation: tuple  # N x (w, x, y, z)
    opacity_logit: tuple  # N
    color: tuple  # N x (r, g, b)
    cam_origin: tuple  # (x, y, z)
    cam_target: tuple
    cam_up: tuple
    width: int
    height: int
    fov_x: float | None  # perspective, or
    ortho_width: float | None  # orthographic
    camera_kind: str  # how the camera was drawn (for the report)

    def surfels(self):
        import mitsuba as mi

        from mi_shadowgs.core.surfels import Surfels

        def cols(values, k):
            a = np.asarray(values, np.float32).reshape(len(self.position), k)
            return [np.ascontiguousarray(a[:, i]) for i in range(k)]

        return Surfels(position=mi.Point3f(*cols(self.position, 3)),
                       log_scale=mi.Point2f(*cols(self.log_scale, 2)),
                       rotation=mi.Vector4f(*cols(self.rotation, 4)),
                       opacity_logit=mi.Float(np.asarray(self.opacity_logit, np.float32)))

    def camera(self):
        from mi_shadowgs.core.camera import Camera

        return Camera.look_at(self.cam_origin, self.cam_target, self.cam_up, width=self.width,
                              height=self.height, fov_x=self.fov_x, ortho_width=self.ortho_width)


def _log10_uniform(lo: float, hi: float):
    return st.floats(math.log10(lo), math.log10(hi)).map(lambda e: 10.0 ** e)


def _unit3():
    return st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: np.linalg.norm(v) > 1e-3) \
        .map(lambda v: tuple(float(x) for x in np.asarray(v) / np.linalg.norm(v)))


def _quaternion():
    direction = st.tuples(*[st.floats(-1.0, 1.0)] * 4).filter(lambda q: np.linalg.norm(q) > 1e-3)
    scaled = st.tuples(direction, st.one_of(_log10_uniform(1e-12, 1e-3), _log10_uniform(1e3, 1e6)))
    axis = st.sampled_from([(1.0, 0.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0),
                            (0.0, 0.0, 0.0, 1.0), (-1.0, 0.0, 0.0, 0.0),
                            (0.5 ** 0.5, 0.5 ** 0.5, 0.0, 0.0)])
    return st.one_of(
        direction,
        axis,
        st.just((0.0, 0.0, 0.0, 0.0)),
        scaled.map(lambda d: tuple(float(x) for x in
                                   np.asarray(d[0]) / np.linalg.norm(d[0]) * d[1])),
    )


def _opacity_logit():
    near_one = _log10_uniform(1e-7, 1e-2).map(lambda e: math.log((1.0 - e) / e))
    return st.one_of(st.floats(-8.0, 8.0), near_one, st.sampled_from([20.0, 60.0, 88.0]))


@st.composite
def fuzz_cases(draw) -> FuzzCase:
    n = draw(st.integers(1, 24))
    coord = st.floats(-1.0, 1.0)
    position = draw(st.lists(st.tuples(coord, coord, coord), min_size=n, max_size=n))
    log_s = st.floats(math.log(1e-6), math.log(1e3))
    log_scale = draw(st.lists(st.tuples(log_s, log_s), min_size=n, max_size=n))
    rotation = draw(st.lists(_quaternion(), min_size=n, max_size=n))
    opacity = draw(st.lists(_opacity_logit(), min_size=n, max_size=n))
    c = st.floats(-2.0, 2.0)
    color = draw(st.lists(st.tuples(c, c, c), min_size=n, max_size=n))

    kind = draw(st.sampled_from(["outside", "inside", "grazing", "far"]))
    if kind == "outside":
        origin = np.asarray(draw(_unit3())) * draw(st.floats(1.5, 10.0))
        target = np.asarray(draw(st.tuples(*[st.floats(-0.3, 0.3)] * 3)))
    elif kind == "inside":
        origin = np.asarray(draw(st.tuples(*[st.floats(-0.8, 0.8)] * 3)))
        target = origin + np.asarray(draw(_unit3()))
    elif kind == "grazing":
        from mi_shadowgs.core.frames import quaternion_to_matrix

        i = draw(st.integers(0, n - 1))
        frame = quaternion_to_matrix(np.asarray([rotation[i]]))[0]  # columns t_u, t_v, n
        p = np.asarray(position[i])
        angle = draw(st.floats(0.0, 2.0 * math.pi))
        in_plane = math.cos(angle) * frame[:, 0] + math.sin(angle) * frame[:, 1]
        off = draw(_log10_uniform(1e-7, 0.1)) * draw(st.sampled_from([-1.0, 1.0]))
        origin = p + draw(st.floats(0.5, 3.0)) * in_plane + off * frame[:, 2]
        target = p
    else:  # far: a shadow-map camera
        origin = np.asarray(draw(_unit3())) * draw(_log10_uniform(50.0, 1000.0))
        target = np.zeros(3)
    if draw(st.booleans()):
        reach = 1.8 if kind == "far" else draw(st.floats(0.05, 2.5))
        dist = float(np.linalg.norm(origin - target))
        fov = 2.0 * math.atan(reach / dist) if kind == "far" else reach
        fov_x, ortho_width = min(fov, 3.0), None
    else:
        fov_x, ortho_width = None, draw(st.floats(0.1, 5.0))
    return FuzzCase(
        position=tuple(position), log_scale=tuple(log_scale), rotation=tuple(rotation),
        opacity_logit=tuple(opacity), color=tuple(color),
        cam_origin=tuple(float(v) for v in origin), cam_target=tuple(float(v) for v in target),
        cam_up=draw(_unit3()), width=draw(st.sampled_from(SIZES)),
        height=draw(st.sampled_from(SIZES)), fov_x=fov_x, ortho_width=ortho_width,
        camera_kind=kind)


def check_case(case: FuzzCase) -> list[str]:
    """What is wrong with the render of ``case`` and its gradients (empty: nothing)."""
    import drjit as dr
    import mitsuba as mi

    from mi_shadowgs.core.raster import AOV_CHANNELS, rasterize

    try:
        s = case.surfels()
        color = mi.TensorXf(np.asarray(case.color, np.float32).reshape(-1, 3))
        params = {**s.params(), "color": color}
        for v in params.values():
            dr.enable_grad(v)
        out = rasterize(s, case.camera(), {"color": color}, aovs=tuple(AOV_CHANNELS))
        loss = mi.Float(0.0)
        for name, img in out.items():
            if name != "count":  # no gradient by design
                w = dr.linspace(mi.Float, 0.5, 1.5, dr.width(img.array))
                loss += dr.sum(img.array * w)
        # Nothing on screen is a valid case: its gradients must be zero, not an error.
        dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
        values = {name: img.numpy() for name, img in out.items()}
        values |= {f"d/d {name}": np.asarray(dr.grad(v)) for name, v in params.items()}
    except Exception as exc:  # a crash is a finding too
        return [f"raised {type(exc).__name__}: {exc}"]
    problems = [f"{name} holds {'NaN' if np.isnan(v).any() else 'Inf'}"
                for name, v in values.items() if not np.isfinite(v).all()]
    alpha = values["alpha"]
    if np.isfinite(alpha).all() and not ((alpha >= 0) & (alpha <= 1 + ALPHA_TOL)).all():
        problems.append(f"alpha outside [0, 1]: {alpha.min()} .. {alpha.max()}")
    return problems


@dataclasses.dataclass
class FuzzResult:
    cases: int  # examples run, shrinking included
    failures: int  # of which failed
    seconds: float
    minimal: FuzzCase | None  # the shrunk failing example
    problems: list[str]

    def summary(self) -> str:
        head = (f"fuzz: {self.cases} cases, {self.failures} failures, "
                f"{self.seconds:.1f} s")
        if self.minimal is None:
            return head
        return (f"{head}\nminimal failing example: {self.minimal!r}\n"
                f"problems: {'; '.join(self.problems)}")


def run_fuzz(cases: int, seed_value: int = 0, shrink: bool = True) -> FuzzResult:
    """``cases`` hypothesis examples from ``seed_value`` (reproducible; no example database);
    ``shrink=False`` reports the first failing example as found."""
    from mi_shadowgs import backend

    backend.set_variant(None)
    stats = {"cases": 0, "failures": 0}
    last: dict = {}

    phases = [Phase.generate, Phase.shrink] if shrink else [Phase.generate]

    @settings(max_examples=cases, deadline=None, database=None, print_blob=False,
              suppress_health_check=list(HealthCheck), phases=phases)
    @seed(seed_value)
    @given(fuzz_cases())
    def prop(case):
        stats["cases"] += 1
        problems = check_case(case)
        if problems:
            stats["failures"] += 1
            last["case"], last["problems"] = case, problems  # the minimal one comes last
            raise AssertionError("; ".join(problems))

    t0 = time.perf_counter()
    try:
        prop()
    except AssertionError:
        pass
    return FuzzResult(stats["cases"], stats["failures"], time.perf_counter() - t0,
                      last.get("case"), last.get("problems", []))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Fuzz the rasterizer for NaN/Inf (hypothesis).")
    ap.add_argument("--cases", type=int, default=1000, help="examples to run (default 1000)")
    ap.add_argument("--seed", type=int, default=0, help="hypothesis seed (default 0)")
    args = ap.parse_args(argv)
    if args.cases < 1:
        ap.error("--cases must be >= 1")
    print(f"fuzz: {args.cases} cases, seed {args.seed}, {os.cpu_count()} cores, "
          f"{platform.processor() or platform.machine()}", flush=True)
    result = run_fuzz(args.cases, args.seed)
    print(result.summary())
    return 1 if result.failures else 0


if __name__ == "__main__":
    sys.exit(main())
