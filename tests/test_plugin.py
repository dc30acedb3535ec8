"""The ``surfel_raster`` integrator: XML loading, film channels, mi.traverse, AD through
mi.render, and the standard Mitsuba optimisation loop."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mi_shadowgs.core.camera import Camera
from mi_shadowgs.core.raster import rasterize
from mi_shadowgs.core.surfels import sh_colors
from mi_shadowgs.io import ply

pytestmark = pytest.mark.usefixtures("plugins")  # every test loads surfel_raster

W, H = 24, 18


def _write_model(path, n=40, seed=0, degree=1):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    model = ply.PlyModel(
        position=rng.uniform(-0.6, 0.6, size=(n, 3)).astype(np.float32),
        log_scale=np.log(rng.uniform(0.08, 0.2, size=(n, 2))).astype(np.float32),
        rotation=rng.normal(size=(n, 4)).astype(np.float32),
        opacity_logit=rng.normal(0.5, 1.0, size=n).astype(np.float32),
        channels={"sh": (0.3 * rng.normal(size=(n, 3 * k))).astype(np.float32),
                  "albedo": rng.uniform(size=(n, 3)).astype(np.float32),
                  "roughness": rng.uniform(size=(n, 1)).astype(np.float32)})
    ply.write_ply_model(path, model)
    return model


def _scene_xml(filename, sensor="perspective", aovs="", extra="", pixel_format="rgba"):
    if sensor == "perspective":
        sens = '<float name="fov" value="45"/>'
        tf = '<lookat origin="0.4, 0.5, 3" target="0, 0, 0" up="0, 1, 0"/>'
    else:
        sens = ""
        tf = '<scale x="1.1" y="1.1"/><lookat origin="0.4, 0.5, 3" target="0, 0, 0" up="0, 1, 0"/>'
    return f"""<scene version="3.0.0">
      <integrator type="surfel_raster" id="surf">
        <string name="filename" value="{filename}"/>
        <string name="aovs" value="{aovs}"/>
        {extra}
      </integrator>
      <sensor type="{sensor}">
        {sens}
        <transform name="to_world">{tf}</transform>
        <film type="hdrfilm"><integer name="width" value="{W}"/>
          <integer name="height" value="{H}"/>
          <string name="pixel_format" value="{pixel_format}"/></film>
      </sensor></scene>"""


@pytest.fixture(scope="module")
def model_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("plugin") / "model.ply"
    _write_model(path)
    return path


def _direct(scene, aovs=("alpha", "depth", "normal"), color="sh", background=None):
    """What the plugin must produce, from ``rasterize`` called directly."""
    integ = scene.integrator()
    cam = Camera.from_mitsuba(scene.sensors()[0])
    s = integ.surfels
    if color == "sh":
        origin = cam.origin - cam.forward * 1.0e4 if cam.is_ortho else cam.origin
        rgb = sh_colors(s, origin)
    else:
        rgb = s.channels[color]
    chans = {"rgb": rgb, **{a: s.channels[a] for a in aovs if a in s.channels}}
    return rasterize(s, cam, chans, aovs=tuple(a for a in aovs if a not in s.channels),
                     background=None if background is None else {"rgb": background})


@pytest.mark.parametrize("sensor", ["perspective", "orthographic"])
def test_render_matches_rasterize(model_path, sensor):
    scene = mi.load_string(_scene_xml(model_path, sensor, aovs="depth,normal,albedo"))
    img = np.asarray(mi.render(scene))
    ref = {k: np.asarray(v) for k, v in
           _direct(scene, aovs=("alpha", "depth", "normal", "albedo")).items()}
    assert img.shape == (H, W, 4 + 1 + 3 + 3)
    expect = np.concatenate([ref["rgb"], ref["alpha"], ref["depth"], ref["normal"],
                             ref["albedo"]], axis=-1)
    # The same kernels on the same inputs: bit-identical (a 24x18 image is one LLVM work
    # block, so even the float atomic adds run in a fixed order).
    np.testing.assert_array_equal(img, expect)
    assert ref["alpha"].max() > 0.5 and (ref["alpha"] == 0).any()  # not a trivial image
    bmp = scene.sensors()[0].film().bitmap()
    names = [f.name for f in bmp.struct_()]
    assert names == ["R", "G", "B", "A", "depth.T", "normal.X", "normal.Y", "normal.Z",
                     "albedo.R", "albedo.G", "albedo.B"]
    np.testing.assert_array_equal(np.asarray(bmp)[..., 4], ref["depth"][..., 0])


def test_color_channel_background_and_rgb_film(model_path):
    extra = ('<string name="color_channel" value="albedo"/>'
             '<rgb name="background" value="0.2, 0.4, 0.6"/>')
    scene = mi.load_string(_scene_xml(model_path, aovs="roughness,alpha", extra=extra,
                                      pixel_format="rgb"))
    img = np.asarray(mi.render(scene))
    ref = {k: np.asarray(v) for k, v in _direct(scene, aovs=("alpha", "roughness"),
                                                color="albedo",
                                                background=(0.2, 0.4, 0.6)).items()}
    assert img.shape == (H, W, 3 + 1 + 1)  # no film alpha: R, G, B, roughness.T, alpha.T
    np.testing.assert_allclose(img[..., :3], ref["rgb"], atol=1e-6)
    np.testing.assert_allclose(img[..., 3:4], ref["roughness"], atol=1e-6)
    np.testing.assert_allclose(img[..., 4:5], ref["alpha"], atol=1e-6)
    # Background pixels show the background colour exactly.
    bg = ref["alpha"][..., 0] == 0
    np.testing.assert_allclose(img[bg][:, :3], np.tile([0.2, 0.4, 0.6], (bg.sum(), 1)),
                               atol=1e-7)


def test_traverse_update_changes_render(model_path):
    scene = mi.load_string(_scene_xml(model_path))
    params = mi.traverse(scene)
    keys = [k for k in params.keys() if k.startswith("surf.")]
    assert keys == ["surf.position", "surf.log_scale", "surf.rotation", "surf.opacity_logit",
                    "surf.channels.sh", "surf.channels.albedo", "surf.channels.roughness"]
    before = np.asarray(mi.render(scene))
    params["surf.opacity_logit"] = dr.full(mi.Float, -20.0, 40)  # nearly transparent
    params.update()
    after = np.asarray(mi.render(scene))
    assert before[..., 3].max() > 0.5
    assert after[..., 3].max() < 1e-6  # opacity 2e-9 < alpha_min: every splat dropped


def _grads_direct(scene, weights):
    s = scene.integrator().surfels
    p = s.params()
    for v in p.values():
        dr.enable_grad(v)
    ref = _direct(scene, aovs=("alpha", "depth"))
    img = dr.concat([ref["rgb"], ref["alpha"], ref["depth"]], axis=-1)
    dr.backward(dr.sum(img * weights, axis=None))
    out = {k: np.asarray(dr.grad(v)).copy() for k, v in p.items()}
    for v in p.values():
        dr.disable_grad(v)
    return out


def test_gradient_through_mi_render_matches_direct(model_path):
    scene = mi.load_string(_scene_xml(model_path, aovs="depth"))
    rng = np.random.default_rng(1)
    weights = mi.TensorXf(rng.normal(size=(H, W, 5)).astype(np.float32))
    params = mi.traverse(scene)
    params.keep(r"surf\..*")
    for k in params.keys():
        dr.enable_grad(params[k])
    img = mi.render(scene, params)
    dr.backward(dr.sum(img * weights, axis=None))
    got = {k[len("surf."):]: np.asarray(dr.grad(params[k])).copy() for k in params.keys()}
    for k in params.keys():
        dr.disable_grad(params[k])
    ref = _grads_direct(scene, weights)
    assert sorted(got) == sorted(ref)
    for k in ref:
        scale = np.abs(ref[k]).max()
        # albedo and roughness are not rendered here: zero gradient.
        assert (scale > 0) == (k not in ("channels.albedo", "channels.roughness")), k
        # Same AD graph; only the order of float atomic adds may differ.
        np.testing.assert_allclose(got[k], ref[k], rtol=0, atol=1e-5 * max(scale, 1e-12),
                                   err_msg=k)


def test_forward_mode_matches_backward(model_path):
    """<d image / d theta . v, w> from render_forward equals <grad_theta <image, w>, v>."""
    scene = mi.load_string(_scene_xml(model_path))
    params = mi.traverse(scene)
    params.keep(r"surf\.channels\.sh|surf\.position")
    rng = np.random.default_rng(2)
    weights = mi.TensorXf(rng.normal(size=(H, W, 4)).astype(np.float32))
    tangent_pos = mi.Point3f(*rng.normal(size=(3, 40)).astype(np.float32))
    dr.enable_grad(params["surf.position"])
    dr.set_grad(params["surf.position"], tangent_pos)
    img = mi.render(scene, params)
    dr.forward_to(img)
    fwd = float(np.asarray(dr.sum(dr.grad(img) * weights, axis=None)))
    dr.disable_grad(params["surf.position"])
    dr.enable_grad(params["surf.position"])
    img = mi.render(scene, params)
    dr.backward(dr.sum(img * weights, axis=None))
    g = np.asarray(dr.grad(params["surf.position"]))
    bwd = float(np.sum(g * np.asarray(tangent_pos)))
    dr.disable_grad(params["surf.position"])
    assert abs(fwd) > 1e-3
    # float32 sums over ~1e3 pixels in different orders.
    assert abs(fwd - bwd) <= 1e-4 * abs(bwd) + 1e-5, (fwd, bwd)


def test_adam_loop_reduces_loss(tmp_path):
    # Target: the model as saved. Start: the same geometry with wrong colours and opacities.
    _write_model(tmp_path / "target.ply", seed=5)
    scene = mi.load_string(_scene_xml(tmp_path / "target.ply"))
    target = mi.TensorXf(np.asarray(mi.render(scene)))
    params = mi.traverse(scene)
    params["surf.channels.sh"] = mi.TensorXf(np.zeros((40, 12), np.float32))
    # Not exactly 0: surfels.stable_sigmoid has a zero derivative at a logit of exactly 0.
    params["surf.opacity_logit"] = dr.full(mi.Float, -0.5, 40)
    params.update()
    opt = mi.ad.Adam(lr=0.1)
    opt["surf.channels.sh"] = params["surf.channels.sh"]
    opt["surf.opacity_logit"] = params["surf.opacity_logit"]
    params.update(opt)
    losses = []
    for it in range(30):
        img = mi.render(scene, params, seed=it)
        loss = dr.mean(dr.square(img - target), axis=None)
        dr.backward(loss)
        opt.step()
        params.update(opt)
        losses.append(float(np.asarray(loss)))
    assert losses[0] > 1e-3
    # Measured: the loss falls to 1.7% of its start in 30 steps; require 10x.
    assert losses[-1] < 0.1 * losses[0], losses


def test_bad_properties_are_named(model_path, tmp_path):
    def load(xml):
        return mi.load_string(xml)

    with pytest.raises(Exception, match="filename"):
        load(_scene_xml(model_path).replace(f'<string name="filename" value="{model_path}"/>',
                                            ""))
    with pytest.raises(Exception, match=r"missing\.ply"):
        load(_scene_xml(tmp_path / "missing.ply"))
    with pytest.raises(Exception, match="unknown AOV 'bogus'"):
        load(_scene_xml(model_path, aovs="depth,bogus"))
    with pytest.raises(Exception, match="colour channel 'metallic'"):
        load(_scene_xml(model_path, extra='<string name="color_channel" value="metallic"/>'))
    with pytest.raises(Exception, match="cutoff_sigma"):
        load(_scene_xml(model_path, extra='<float name="cutoff_sigma" value="-1"/>'))


@pytest.mark.cuda
def test_cuda_render_matches_llvm(model_path, request):
    """The plugin on cuda_ad_rgb renders what it renders on llvm_ad_rgb, and differentiates."""
    xml = _scene_xml(model_path, aovs="depth,normal")
    llvm_img = np.asarray(mi.render(mi.load_string(xml)))
    request.getfixturevalue("cuda_variant")
    scene = mi.load_string(xml)
    params = mi.traverse(scene)
    params.keep(r"surf\.position")
    dr.enable_grad(params["surf.position"])
    img = mi.render(scene, params)
    dr.backward(dr.sum(img, axis=None))
    grad = np.asarray(dr.grad(params["surf.position"]))
    # Different hardware, same float32 maths: only summation order and fused ops differ.
    np.testing.assert_allclose(np.asarray(img), llvm_img, atol=1e-4)
    assert np.isfinite(grad).all() and np.abs(grad).max() > 0


def test_relative_filename_and_grey_background(tmp_path):
    _write_model(tmp_path / "rel.ply", seed=3)
    xml = _scene_xml("rel.ply", extra='<float name="background" value="0.5"/>')
    (tmp_path / "scene.xml").write_text(xml)
    scene = mi.load_file(str(tmp_path / "scene.xml"))  # resolves rel.ply beside the scene
    assert scene.integrator().filename == str(tmp_path / "rel.ply")
    img = np.asarray(mi.render(scene))
    empty = img[..., 3] == 0
    assert empty.any()
    np.testing.assert_array_equal(img[empty][:, :3], 0.5)


def test_sensors_and_settings_it_cannot_honour_are_refused(model_path):
    """A thinlens sensor was drawn as a pinhole (no depth of field), an alpha_min at or above
    alpha_max drew an empty image, and a colour channel of another width failed at render
    time only; each is now an error naming it."""
    thinlens = _scene_xml(model_path).replace(
        '<sensor type="perspective">',
        '<sensor type="thinlens"><float name="aperture_radius" value="0.3"/>'
        '<float name="focus_distance" value="1"/>')
    with pytest.raises(Exception) as err:  # mi.render chains the plugin's error
        mi.render(mi.load_string(thinlens))
    assert "unsupported sensor ThinLensCamera" in str(err.value.__cause__ or err.value)
    with pytest.raises(Exception, match="'alpha_min' .* must be below 'alpha_max'"):
        mi.load_string(_scene_xml(model_path, extra='<float name="alpha_min" value="0.995"/>'))
    path = model_path.with_name("wide.ply")
    model = _write_model(path)
    model.channels["feature"] = np.zeros((model.count, 5), np.float32)
    ply.write_ply_model(path, model)
    with pytest.raises(Exception, match="colour channel 'feature' has 5 columns"):
        mi.load_string(_scene_xml(path, extra='<string name="color_channel" value="feature"/>'))


def test_params_update_to_a_model_it_cannot_draw_is_named(model_path):
    """After params.update(), a model of 0 surfels failed inside the rasterizer ('Point3f
    .__sub__(): nested operation failed') and an SH channel of another width inside eval_sh;
    both are refused at the update, naming the parameter."""
    scene = mi.load_string(_scene_xml(model_path))
    params = mi.traverse(scene)
    params["surf.channels.sh"] = mi.TensorXf(np.zeros((40, 5), np.float32))
    with pytest.raises(ValueError, match=r"'channels.sh'.* 5 columns"):
        params.update()
    scene = mi.load_string(_scene_xml(model_path))
    params = mi.traverse(scene)
    for key in params.keys():
        if key.startswith("surf."):
            value = params[key]
            params[key] = mi.TensorXf(np.zeros((0, value.shape[1]), np.float32)) \
                if isinstance(value, mi.TensorXf) else dr.zeros(type(value), 0)
    with pytest.raises(ValueError, match="'position' has 0 entries"):
        params.update()


def _with(value, row, col, x):
    """``value`` (a traversed parameter) with entry [row, col] set to ``x``."""
    a = np.array(value)
    if isinstance(value, mi.TensorXf) or a.ndim == 1:
        a.reshape(a.shape[0], -1)[row, col] = x
    else:  # a Point3f etc. is [3, N]
        a[col, row] = x
    return type(value)(a)


def _zero_quaternion(value, row, scale):
    a = np.array(value)
    a[:, row] = scale
    return type(value)(a)


@pytest.mark.parametrize("key, change, match", [
    pytest.param("position", lambda v: _with(v, 7, 1, np.nan),
                 r"'position' holds NaN at vertex 7 \(1 of", id="nan-position"),
    pytest.param("log_scale", lambda v: _with(v, 3, 0, np.inf),
                 r"'log_scale' holds Inf at vertex 3 \(1 of", id="inf-log_scale"),
    pytest.param("opacity_logit", lambda v: _with(v, 0, 0, -np.inf),
                 r"'opacity_logit' holds Inf at vertex 0", id="inf-opacity"),
    pytest.param("rotation", lambda v: _with(v, 5, 2, np.nan),
                 r"'rotation' holds NaN at vertex 5", id="nan-rotation"),
    pytest.param("channels.sh", lambda v: _with(v, 11, 4, np.nan),
                 r"'channels.sh' holds NaN at vertex 11", id="nan-sh"),
    pytest.param("channels.albedo", lambda v: _with(v, 2, 1, np.inf),
                 r"'channels.albedo' holds Inf at vertex 2", id="inf-albedo"),
    pytest.param("rotation", lambda v: _zero_quaternion(v, 9, 0.0),
                 r"rotation \(w, x, y, z\) hold a zero quaternion .* at vertex 9 \(1 of",
                 id="zero-quaternion"),
    # |q|^2 = 4e-60 underflows float32: the kernels drew it as the identity, like a zero.
    pytest.param("rotation", lambda v: _zero_quaternion(v, 9, 1e-30),
                 r"zero quaternion .* at vertex 9", id="1e-30-quaternion"),
    # exp(-100) is 0 in float32 (a surfel of no extent), exp(30) is over 1e12: the PLY
    # reader refuses both.
    pytest.param("log_scale", lambda v: _with(v, 6, 1, -100.0),
                 r"'log_scale\[:, 1\]' holds a log-scale whose exp is zero .* at vertex 6",
                 id="log_scale-under"),
    pytest.param("log_scale", lambda v: _with(v, 4, 0, 30.0),
                 r"'log_scale\[:, 0\]' holds a log-scale above 27.63 .* at vertex 4",
                 id="log_scale-over"),
])
@pytest.mark.parametrize("traversed", ["scene", "integrator"])
def test_params_update_refuses_nan_inf_and_zero_quaternions(model_path, key, change, match,
                                                            traversed):
    """A NaN or Inf set through mi.traverse (a diverged optimiser step) rendered silently:
    NaN/Inf geometry or opacity dropped the surfel, a NaN quaternion or a zero one drew it
    with the identity orientation, a non-finite channel gave NaN pixels. params.update() now
    refuses each, naming the plugin, the parameter and the first bad row, as the PLY
    reader does. Inside a scene Mitsuba names a changed channel by its last part ('sh');
    traversed alone, by its whole key ('channels.sh'): both are checked."""
    scene = mi.load_string(_scene_xml(model_path, aovs="albedo"))
    params = mi.traverse(scene if traversed == "scene" else scene.integrator())
    prefix = "surf." if traversed == "scene" else ""
    params[prefix + key] = change(params[prefix + key])
    with pytest.raises(ValueError, match=r"^surfel_raster: params.update\(\): .*" + match):
        params.update()


def test_a_finite_params_update_renders_and_differentiates(model_path):
    """The check of params.update() runs with gradients suspended: values set with their
    gradients enabled (as mi.ad.Adam's are) stay attached, and mi.render(scene, params)
    renders the new values and differentiates them as rasterize does."""
    scene = mi.load_string(_scene_xml(model_path, aovs="depth"))
    params = mi.traverse(scene)
    params.keep(r"surf\..*")
    rng = np.random.default_rng(4)
    for k in params.keys():  # every parameter changed, finite, grad enabled before update
        a = np.array(params[k])
        value = type(params[k])(a + (0.02 * rng.normal(size=a.shape)).astype(np.float32))
        dr.enable_grad(value)
        params[k] = value
    params.update()
    assert all(dr.grad_enabled(params[k]) for k in params.keys())
    weights = mi.TensorXf(rng.normal(size=(H, W, 5)).astype(np.float32))
    img = mi.render(scene, params)
    dr.backward(dr.sum(img * weights, axis=None))
    got = {k[len("surf."):]: np.asarray(dr.grad(params[k])).copy() for k in params.keys()}
    for k in params.keys():
        dr.disable_grad(params[k])
    ref_img = _direct(scene, aovs=("alpha", "depth"))
    np.testing.assert_array_equal(np.asarray(img), np.concatenate(
        [np.asarray(ref_img[c]) for c in ("rgb", "alpha", "depth")], axis=-1))
    ref = _grads_direct(scene, weights)
    for k in ref:
        scale = np.abs(ref[k]).max()
        assert (scale > 0) == (k not in ("channels.albedo", "channels.roughness")), k
        # Same AD graph; only the order of float atomic adds may differ.
        np.testing.assert_allclose(got[k], ref[k], rtol=0, atol=1e-5 * max(scale, 1e-12),
                                   err_msg=k)


def test_a_refused_params_update_leaves_the_accepted_values(model_path):
    """Mitsuba writes the new values into the parameters before parameters_changed sees
    them: a refused update used to leave the NaN in the integrator, drawn at the next
    render. Now the values of the last accepted update stand, and the next good update is
    taken."""
    scene = mi.load_string(_scene_xml(model_path))
    params = mi.traverse(scene)
    before = np.asarray(mi.render(scene)).copy()
    original = {k: np.array(params[k]) for k in params.keys() if k.startswith("surf.")}
    moved = _with(params["surf.position"], 3, 0, 0.05 + original["surf.position"][0, 3])
    params["surf.position"] = moved
    params.update()
    accepted = np.asarray(mi.render(scene)).copy()
    assert not np.array_equal(accepted, before)
    params["surf.position"] = _with(params["surf.position"], 7, 1, np.nan)
    params["surf.channels.sh"] = mi.TensorXf(np.zeros((40, 5), np.float32))
    with pytest.raises(ValueError, match="'position' holds NaN at vertex 7"):
        params.update()
    np.testing.assert_array_equal(np.array(params["surf.position"]), np.array(moved))
    assert params["surf.channels.sh"].shape == tuple(original["surf.channels.sh"].shape)
    np.testing.assert_array_equal(np.asarray(mi.render(scene)), accepted)
    # The next update that is good is taken, from the accepted values.
    params["surf.opacity_logit"] = mi.Float(np.full(40, -2.0, np.float32))
    params.update()
    np.testing.assert_array_equal(np.array(params["surf.position"]), np.array(moved))
    after = np.asarray(mi.render(scene))
    assert np.abs(after - accepted).max() > 1e-3


def test_sh_space_turns_display_sh_linear(tmp_path):
    """`sh_space` (default: the PLY's record, else linear): another tool's display SH given
    `srgb` render as the linear SH they came from; an export's record does it unasked; a
    value that is no colour space is named."""
    model = _write_model(tmp_path / "linear.ply")
    model.channels["sh"][:, :3] *= 0.5  # view-mean colours inside [0, 1]: exact round trip
    ply.write_ply_model(tmp_path / "linear.ply", model)
    display = ply.PlyModel(model.position, model.log_scale, model.rotation, model.opacity_logit,
                           {"sh": ply.sh_to_srgb(model.channels["sh"])})
    ply.write_ply_model(tmp_path / "foreign.ply", display)
    ply.write_ply_model(tmp_path / "exported.ply", display, {"sh_space": "srgb"})

    def rgb(name, extra=""):
        scene = mi.load_string(_scene_xml(tmp_path / name, extra=extra))
        return np.asarray(mi.render(scene))[..., :3]

    truth = rgb("linear.ply")
    assert truth.max() > 0.1
    told = rgb("foreign.ply", '<string name="sh_space" value="srgb"/>')
    np.testing.assert_allclose(told, truth, atol=1e-4)
    np.testing.assert_allclose(rgb("exported.ply"), truth, atol=1e-4)
    assert np.abs(rgb("foreign.ply") - truth).max() > 0.05  # read as linear: washed out
    with pytest.raises(Exception, match="property 'sh_space' must be one of linear, srgb"):
        rgb("foreign.ply", '<string name="sh_space" value="gamma"/>')
