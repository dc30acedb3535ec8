"""PLY I/O in the public 2DGS layout: round trips, byte layout, SH reordering, bad files."""

from __future__ import annotations

import numpy as np
import pytest

from mi_shadowgs.io import ply


def _model(n=7, degree=3, seed=0, extra=True):
    rng = np.random.default_rng(seed)
    k = (degree + 1) ** 2
    channels = {"sh": rng.normal(size=(n, 3 * k)).astype(np.float32)}
    if extra:
        channels.update(albedo=rng.uniform(size=(n, 3)).astype(np.float32),
                        roughness=rng.uniform(size=(n, 1)).astype(np.float32),
                        feature=rng.normal(size=(n, 16)).astype(np.float32),
                        segment=rng.integers(0, 5, size=(n, 1)).astype(np.float32))
    return ply.PlyModel(position=rng.normal(size=(n, 3)).astype(np.float32),
                        log_scale=rng.normal(-3, 1, size=(n, 2)).astype(np.float32),
                        rotation=rng.normal(size=(n, 4)).astype(np.float32),
                        opacity_logit=rng.normal(size=n).astype(np.float32),
                        channels=channels)


def _assert_models_equal(a: ply.PlyModel, b: ply.PlyModel):
    # float32 stored as float32: the round trip must be bit-exact.
    for field in ("position", "log_scale", "rotation", "opacity_logit"):
        np.testing.assert_array_equal(getattr(a, field), getattr(b, field), err_msg=field)
    assert sorted(a.channels) == sorted(b.channels)
    for name in a.channels:
        np.testing.assert_array_equal(a.channels[name], b.channels[name], err_msg=name)


def test_sh_layout_matches_3dgs_channel_major():
    n, k = 4, 16
    sh = np.arange(n * k * 3, dtype=np.float32).reshape(n, k * 3)
    f_dc, f_rest = ply.sh_to_dc_rest(sh)
    for i in range(n):
        for c in range(3):
            assert f_dc[i, c] == sh[i, c]
            for kk in range(1, k):
                assert f_rest[i, c * (k - 1) + kk - 1] == sh[i, kk * 3 + c]
    np.testing.assert_array_equal(ply.dc_rest_to_sh(f_dc, f_rest), sh)


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_all_channels(tmp_path, degree):
    m = _model(degree=degree)
    path = tmp_path / "m.ply"
    ply.write_ply_model(path, m)
    _assert_models_equal(m, ply.read_ply_model(path))


def test_round_trip_without_sh_and_empty(tmp_path):
    m = _model(extra=True)
    del m.channels["sh"]
    ply.write_ply_model(tmp_path / "a.ply", m)
    back = ply.read_ply_model(tmp_path / "a.ply")
    _assert_models_equal(m, back)
    assert "f_dc_0" not in ply.read_ply_vertices(tmp_path / "a.ply")
    empty = _model(n=0, extra=False)
    ply.write_ply_model(tmp_path / "e.ply", empty)
    assert ply.read_ply_vertices(tmp_path / "e.ply")["x"].shape == (0,)
    with pytest.raises(ply.PlyError, match=r"e\.ply: no surfels"):  # not a surfel model
        ply.read_ply_model(tmp_path / "e.ply")


def test_byte_layout_is_2dgs(tmp_path):
    n, degree = 5, 3
    m = _model(n=n, degree=degree, extra=False)
    m.channels["albedo"] = np.full((n, 3), 0.25, np.float32)
    m.channels["segment"] = np.arange(n, dtype=np.float32)[:, None]
    path = tmp_path / "m.ply"
    ply.write_ply_model(path, m)
    data = path.read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    names = (["x", "y", "z", "nx", "ny", "nz"] + [f"f_dc_{i}" for i in range(3)]
             + [f"f_rest_{i}" for i in range(45)] + ["opacity", "scale_0", "scale_1"]
             + [f"rot_{i}" for i in range(4)] + ["albedo_0", "albedo_1", "albedo_2", "segment"])
    assert header == (["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
                      + [f"property float {p}" for p in names] + ["end_header"])
    body = np.frombuffer(data[end:], dtype="<f4")
    assert body.size == n * len(names)
    rows = body.reshape(n, len(names))
    col = {p: i for i, p in enumerate(names)}
    np.testing.assert_array_equal(rows[:, col["x"]], m.position[:, 0])
    np.testing.assert_array_equal(rows[:, col["opacity"]], m.opacity_logit)
    np.testing.assert_array_equal(rows[:, col["scale_1"]], m.log_scale[:, 1])
    np.testing.assert_array_equal(rows[:, col["rot_0"]], m.rotation[:, 0])
    # f_rest_{c*15 + k-1} holds SH coefficient k of colour channel c.
    np.testing.assert_array_equal(rows[:, col["f_rest_16"]], m.channels["sh"][:, 2 * 3 + 1])
    np.testing.assert_array_equal(rows[:, col["segment"]], np.arange(n))
    # Normals are the rotation's third column: unit length.
    np.testing.assert_allclose(np.linalg.norm(rows[:, 3:6], axis=1), 1.0, atol=1e-6)


def _write_foreign(path, fmt, n=3):
    """A file as the 2DGS code writes it (zero normals, degree 1), independent of our writer."""
    rng = np.random.default_rng(3)
    names = (["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
             + [f"f_rest_{i}" for i in range(9)]
             + ["opacity", "scale_0", "scale_1", "rot_0", "rot_1", "rot_2", "rot_3"])
    vals = rng.normal(size=(n, len(names)))
    vals[:, 3:6] = 0.0
    ptype = "double" if fmt == "ascii" else "float"
    head = (f"ply\nformat {fmt} 1.0\ncomment written by hand\nelement vertex {n}\n"
            + "".join(f"property {ptype} {p}\n" for p in names) + "end_header\n")
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in vals).encode()
    else:
        body = vals.astype(">f4" if fmt == "binary_big_endian" else "<f4").tobytes()
    path.write_bytes(head.encode() + body)
    return names, vals


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian", "binary_big_endian"])
def test_reads_foreign_files(tmp_path, fmt):
    names, vals = _write_foreign(tmp_path / "f.ply", fmt)
    m = ply.read_ply_model(tmp_path / "f.ply")
    col = {p: i for i, p in enumerate(names)}
    # ascii doubles are rounded once to float32; binary floats are exact.
    np.testing.assert_array_equal(m.position, vals[:, :3].astype(np.float32))
    np.testing.assert_array_equal(m.rotation, vals[:, col["rot_0"]:].astype(np.float32))
    sh = m.channels["sh"]
    assert sh.shape == (3, 12) and sorted(m.channels) == ["sh"]
    # coefficient k=2 of green (c=1) sits at f_rest[c*3 + k-1] = f_rest_4.
    np.testing.assert_array_equal(sh[:, 2 * 3 + 1], vals[:, col["f_rest_4"]].astype(np.float32))


def test_errors_name_file_and_property(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.ply"):
        ply.read_ply_model(tmp_path / "nope.ply")
    (tmp_path / "bad.ply").write_bytes(b"OFF\n3 1 0\n")
    with pytest.raises(ply.PlyError, match=r"bad\.ply.*not a PLY"):
        ply.read_ply_model(tmp_path / "bad.ply")
    ply.write_ply_vertices(tmp_path / "miss.ply", {"x": np.zeros(2), "y": np.zeros(2),
                                                   "z": np.zeros(2), "opacity": np.zeros(2)})
    with pytest.raises(ply.PlyError, match=r"miss\.ply.*scale_0, scale_1, rot_0"):
        ply.read_ply_model(tmp_path / "miss.ply")
    m = _model(n=4, extra=True)
    m.channels["albedo"][2, 1] = np.nan
    ply.write_ply_model(tmp_path / "nan.ply", m)
    with pytest.raises(ply.PlyError, match=r"nan\.ply.*'albedo_1'.*NaN.*vertex 2"):
        ply.read_ply_model(tmp_path / "nan.ply")
    full = (tmp_path / "nan.ply").read_bytes()
    (tmp_path / "short.ply").write_bytes(full[:-10])
    with pytest.raises(ply.PlyError, match=r"short\.ply.*truncated"):
        ply.read_ply_model(tmp_path / "short.ply")
    m = _model(n=2, extra=False)
    m.channels["rough_1"] = np.zeros((2, 1), np.float32)
    with pytest.raises(ply.PlyError, match="rough_1"):
        ply.write_ply_model(tmp_path / "x.ply", m)
    assert not (tmp_path / "x.ply").exists()
    # The 2DGS loader reads every property starting with "rot" as a quaternion component.
    m = _model(n=2, extra=False)
    m.channels["rotation_offset"] = np.zeros((2, 2), np.float32)
    with pytest.raises(ply.PlyError, match="rotation_offset"):
        ply.write_ply_model(tmp_path / "x.ply", m)


def test_surfels_round_trip(tmp_path):
    from mi_shadowgs.core import surfels as surfels_mod

    m = _model(n=6)
    s = m.to_surfels()
    assert isinstance(s, surfels_mod.Surfels) and s.count == 6
    ply.save_ply(tmp_path / "s.ply", s)
    back = ply.load_ply(tmp_path / "s.ply")
    _assert_models_equal(m, ply.PlyModel.from_surfels(back))
    # The activated view agrees with the raw file values.
    act = back.to_numpy()
    np.testing.assert_allclose(act["scale"], np.exp(m.log_scale.astype(np.float64)), rtol=1e-6)
    np.testing.assert_allclose(act["opacity"], 1 / (1 + np.exp(-m.opacity_logit.astype(float))),
                               rtol=1e-6)


def test_metadata_round_trips_as_comments_other_readers_skip(tmp_path):
    model = _model(12, 1)
    path = tmp_path / "m.ply"
    ply.write_ply_model(path, model, {"receiver_band": "0.5", "fit": "full"})
    assert ply.read_ply_metadata(path) == {"receiver_band": "0.5", "fit": "full"}
    header = path.read_bytes().split(b"end_header")[0].decode()
    assert "comment mi_shadowgs receiver_band 0.5\n" in header
    back = ply.read_ply_model(path)  # the vertices read as before
    np.testing.assert_array_equal(back.position, model.position)
    plyfile = pytest.importorskip("plyfile", reason="plyfile: the reader other tools use")
    assert len(plyfile.PlyData.read(str(path))["vertex"]) == 12
    ply.write_ply_model(tmp_path / "plain.ply", model)
    assert ply.read_ply_metadata(tmp_path / "plain.ply") == {}


@pytest.mark.parametrize("key, value", [("band", "0 .5"), ("band", ""), ("2band", "1"),
                                        ("band", "\u00b5")])
def test_metadata_that_cannot_be_a_comment_is_refused(tmp_path, key, value):
    with pytest.raises(ply.PlyError, match="cannot be a PLY comment"):
        ply.write_ply_model(tmp_path / "m.ply", _model(3, 0), {key: value})
    assert not (tmp_path / "m.ply").exists()


def _srgb_curve(x):
    """IEC 61966-2-1, restated here so that the test does not lean on io.images."""
    x = np.clip(np.asarray(x, np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * x ** (1 / 2.4) - 0.055)


def _sh_rgb(sh, d):
    """Colour + 0.5 of degree-1 SH [N, 12] (coefficient-major) along unit ``d`` [3], float64:
    3DGS's real basis, C1 = sqrt(3 / (4 pi)), -y, z, -x."""
    c = sh.reshape(len(sh), 4, 3).astype(np.float64)
    c1 = np.sqrt(3.0 / (4.0 * np.pi))
    basis = [ply.SH_C0, -c1 * d[1], c1 * d[2], -c1 * d[0]]
    return sum(b * c[:, k] for k, b in enumerate(basis)) + 0.5


def test_display_sh_round_trip_and_first_order_colours():
    """``sh_from_srgb`` undoes ``sh_to_srgb`` (view-mean colours inside [0, 1]); the display
    SH's DC colour is the sRGB of the linear one exactly, and along any direction the
    colours agree to first order in the higher bands.

    Tolerance: the bands move a colour by at most 0.02 C1 = 0.0098 along an axis; the
    second-order term 0.5 |f''| 0.0098^2 of the sRGB curve f is 4.7e-4 at a colour of 0.1,
    so 1e-3 (darker colours bend more: 6e-3 at 0.02)."""
    rng = np.random.default_rng(5)
    n = 200
    sh = np.zeros((n, 12), np.float32)
    dc_colour = rng.uniform(0.1, 0.98, size=(n, 3))
    sh[:, :3] = (dc_colour - 0.5) / ply.SH_C0
    sh[:, 3:] = rng.uniform(-0.02, 0.02, size=(n, 9))
    display = ply.sh_to_srgb(sh)
    np.testing.assert_allclose(ply.sh_from_srgb(display), sh, rtol=1e-5, atol=2e-6)
    np.testing.assert_allclose(ply.SH_C0 * display[:, :3] + 0.5, _srgb_curve(dc_colour),
                               atol=2e-6)
    for d in np.eye(3):
        shown = _sh_rgb(display, d)
        np.testing.assert_allclose(shown, _srgb_curve(_sh_rgb(sh, d)), atol=1e-3)


def test_a_display_sh_record_is_read_as_linear_and_bad_spaces_are_named(tmp_path):
    """A PLY recording ``sh_space srgb`` (our export's) comes back with the linear SH it was
    made from; without the record it is read as linear unless ``sh_space`` says otherwise;
    an unknown record or argument is refused by name."""
    m = _model(n=9, degree=1, extra=False)
    m.channels["sh"][:, :3] = 0.1 * m.channels["sh"][:, :3]  # DC colours inside [0, 1]
    m.channels["sh"][:, 3:] = 0.01 * m.channels["sh"][:, 3:]
    display = ply.PlyModel(m.position, m.log_scale, m.rotation, m.opacity_logit,
                           {"sh": ply.sh_to_srgb(m.channels["sh"])})
    ply.write_ply_model(tmp_path / "display.ply", display, {"sh_space": "srgb"})
    back = ply.read_ply_model(tmp_path / "display.ply")
    np.testing.assert_allclose(back.channels["sh"], m.channels["sh"], rtol=1e-5, atol=2e-6)
    raw = ply.read_ply_model(tmp_path / "display.ply", sh_space="linear")
    np.testing.assert_array_equal(raw.channels["sh"], display.channels["sh"])

    ply.write_ply_model(tmp_path / "foreign.ply", display)  # another tool's: no record
    assert ply.sh_space_of(tmp_path / "foreign.ply") == "linear"
    np.testing.assert_array_equal(ply.read_ply_model(tmp_path / "foreign.ply").channels["sh"],
                                  display.channels["sh"])
    told = ply.read_ply_model(tmp_path / "foreign.ply", sh_space="srgb")
    np.testing.assert_allclose(told.channels["sh"], m.channels["sh"], rtol=1e-5, atol=2e-6)

    ply.write_ply_model(tmp_path / "bad.ply", m, {"sh_space": "rec2020"})
    with pytest.raises(ply.PlyError, match=r"bad\.ply.*'sh_space' is 'rec2020'"):
        ply.read_ply_model(tmp_path / "bad.ply")
    with pytest.raises(ply.PlyError, match=r"sh_space must be one of linear, srgb, got 'sRGB'"):
        ply.load_ply(tmp_path / "foreign.ply", sh_space="sRGB")
