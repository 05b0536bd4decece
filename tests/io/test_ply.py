"""Gaussians .ply reader/writer against plyfile and trimesh (third-party readers), analytic
activations of independently written files, and the golden files in formats/examples/."""

from __future__ import annotations

import math

import numpy as np
import plyfile
import pytest
import torch
import trimesh

from dlacli.errors import DlaInputError
from dlacli.io.ply import read_ply, summarize_ply, write_ply
from dlacli.types import Gaussians

SQRT_PI = math.sqrt(math.pi)


def inria_names(degree: int) -> list[str]:
    """The INRIA property order, spelled out independently of dlacli.io.ply."""
    n_rest = {0: 0, 1: 9, 2: 24, 3: 45}[degree]
    return (
        ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2"]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    )


def random_gaussians(n: int, degree: int, seed: int = 0) -> Gaussians:
    g = torch.Generator().manual_seed(seed)
    quats = torch.randn(n, 4, generator=g)
    quats = quats / quats.norm(dim=1, keepdim=True)
    return Gaussians(
        means=torch.randn(n, 3, generator=g),
        quats=quats,
        scales=torch.rand(n, 3, generator=g) * 0.2 + 1e-3,
        opacities=torch.rand(n, generator=g) * 0.98 + 0.01,
        sh=torch.randn(n, (degree + 1) ** 2, 3, generator=g),
    )


def stored_rows(n: int, degree: int, seed: int = 1) -> dict[str, np.ndarray]:
    """Random stored-space values (logits, log scales, unnormalised quaternions), float64."""
    rng = np.random.default_rng(seed)
    cols = {name: rng.normal(size=n) for name in inria_names(degree)}
    cols["opacity"] = rng.uniform(-4, 4, size=n)
    for i in range(3):
        cols[f"scale_{i}"] = rng.uniform(-6, 0, size=n)
    for i in range(4):
        cols[f"rot_{i}"] = rng.uniform(0.5, 2.0, size=n) * np.sign(rng.normal(size=n))
    return cols


def write_with_plyfile(path, cols: dict[str, np.ndarray], dtype="<f4", text=False, byte_order="<"):
    names = list(cols)
    n = len(cols[names[0]])
    arr = np.empty(n, dtype=[(name, dtype) for name in names])
    for name in names:
        arr[name] = cols[name]
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "vertex")], text=text, byte_order=byte_order).write(str(path))


def expected_activated(cols: dict[str, np.ndarray], degree: int):
    """Analytic activations of stored columns (float64), with the channel-major f_rest layout."""
    n = len(cols["x"])
    k = (degree + 1) ** 2
    means = np.stack([cols["x"], cols["y"], cols["z"]], 1)
    opac = 1.0 / (1.0 + np.exp(-cols["opacity"]))
    scales = np.exp(np.stack([cols[f"scale_{i}"] for i in range(3)], 1))
    rots = np.stack([cols[f"rot_{i}"] for i in range(4)], 1)
    quats = rots / np.linalg.norm(rots, axis=1, keepdims=True)
    sh = np.zeros((n, k, 3))
    for c in range(3):
        sh[:, 0, c] = cols[f"f_dc_{c}"]
        for j in range(1, k):
            sh[:, j, c] = cols[f"f_rest_{c * (k - 1) + (j - 1)}"]
    return means, quats, scales, opac, sh


def assert_gaussians_close(g: Gaussians, expected, rtol=2e-6, atol=1e-7):
    means, quats, scales, opac, sh = expected
    for got, want in zip((g.means, g.quats, g.scales, g.opacities, g.sh), (means, quats, scales, opac, sh)):
        assert got.dtype == torch.float32
        np.testing.assert_allclose(got.numpy(), want, rtol=rtol, atol=atol)


# --- writer, checked with third-party readers -------------------------------------------------


@pytest.mark.parametrize("degree", [0, 3])
def test_written_ply_opens_in_plyfile_with_inria_layout(tmp_path, degree):
    g = random_gaussians(40, degree)
    path = tmp_path / "g.ply"
    write_ply(g, path)
    ply = plyfile.PlyData.read(str(path))
    assert not ply.text and ply.byte_order == "<"
    assert [el.name for el in ply.elements] == ["vertex"]
    vertex = ply["vertex"]
    assert [p.name for p in vertex.properties] == inria_names(degree)
    assert all(vertex.data.dtype[name] == np.dtype("<f4") for name in inria_names(degree))
    data = {name: vertex.data[name].astype(np.float64) for name in inria_names(degree)}
    np.testing.assert_array_equal(np.stack([data["x"], data["y"], data["z"]], 1), g.means.numpy())
    assert not any(data[n].any() for n in ("nx", "ny", "nz"))
    op = g.opacities.double().numpy()
    np.testing.assert_allclose(data["opacity"], np.log(op / (1 - op)), rtol=1e-5, atol=1e-6)
    for i in range(3):
        np.testing.assert_allclose(data[f"scale_{i}"], np.log(g.scales[:, i].double().numpy()), rtol=1e-6)
    for i in range(4):
        np.testing.assert_allclose(data[f"rot_{i}"], g.quats[:, i].numpy(), atol=1e-6)
    k = (degree + 1) ** 2
    for c in range(3):
        np.testing.assert_array_equal(data[f"f_dc_{c}"], g.sh[:, 0, c].numpy())
        for j in range(1, k):  # channel-major: all of R's higher coefficients, then G's, then B's
            np.testing.assert_array_equal(data[f"f_rest_{c * (k - 1) + j - 1}"], g.sh[:, j, c].numpy())


def test_written_ply_opens_in_trimesh_as_point_cloud(tmp_path):
    g = random_gaussians(25, 1)
    path = tmp_path / "g.ply"
    write_ply(g, path)
    cloud = trimesh.load(str(path))
    assert isinstance(cloud, trimesh.PointCloud)
    assert len(cloud.vertices) == 25
    np.testing.assert_allclose(cloud.vertices, g.means.numpy(), rtol=0, atol=0)


def test_write_is_atomic_on_failure(tmp_path, monkeypatch):
    path = tmp_path / "g.ply"
    write_ply(random_gaussians(5, 0), path)
    before = path.read_bytes()

    def boom(self, stream):
        with open(stream, "wb") as f:
            f.write(b"ply\nhalf a file")
        raise OSError("disk full")

    monkeypatch.setattr(plyfile.PlyData, "write", boom)
    with pytest.raises(OSError):
        write_ply(random_gaussians(7, 0, seed=3), path)
    assert path.read_bytes() == before
    assert [p.name for p in tmp_path.iterdir()] == ["g.ply"]


def test_write_rejects_bad_gaussians(tmp_path):
    g = random_gaussians(4, 0)
    g.scales[1, 2] = 0.0
    with pytest.raises(DlaInputError, match="scales"):
        write_ply(g, tmp_path / "g.ply")
    g = random_gaussians(4, 0)
    g.means[0, 0] = float("nan")
    with pytest.raises(DlaInputError, match="means"):
        write_ply(g, tmp_path / "g.ply")
    assert not (tmp_path / "g.ply").exists()


# --- reader, on files written independently with plyfile ------------------------------------


@pytest.mark.parametrize(
    "degree, dtype, text, byte_order",
    [
        (0, "<f4", False, "<"),
        (3, "<f4", False, "<"),
        (1, ">f4", False, ">"),  # big-endian
        (2, "<f4", True, "<"),  # ascii
        (3, "<f8", False, "<"),  # float64 properties
        (3, ">f8", True, ">"),
    ],
)
def test_reads_independent_files_exactly(tmp_path, degree, dtype, text, byte_order):
    cols = stored_rows(30, degree)
    path = tmp_path / "ext.ply"
    write_with_plyfile(path, cols, dtype=dtype, text=text, byte_order=byte_order)
    if dtype.endswith("f4"):  # the reader sees float32-rounded stored values
        cols = {k: v.astype(np.float32).astype(np.float64) for k, v in cols.items()}
    assert_gaussians_close(read_ply(path), expected_activated(cols, degree))


def test_ignores_extra_properties_and_missing_normals(tmp_path):
    cols = stored_rows(12, 1)
    for name in ("nx", "ny", "nz"):
        del cols[name]
    cols = {"red_channel_extra": np.arange(12.0), **cols, "filter_3D": np.ones(12)}
    path = tmp_path / "extra.ply"
    write_with_plyfile(path, cols)
    cols = {k: v.astype(np.float32).astype(np.float64) for k, v in cols.items()}
    assert_gaussians_close(read_ply(path), expected_activated(cols, 1))
    summary = summarize_ply(path)
    assert summary["extra_properties"] == ["red_channel_extra", "filter_3D"]
    assert summary["count"] == 12 and summary["sh_degree"] == 1


def test_zero_vertices_is_an_empty_scene(tmp_path):
    path = tmp_path / "empty.ply"
    write_with_plyfile(path, {name: np.zeros(0) for name in inria_names(0)})
    g = read_ply(path)
    assert len(g) == 0 and g.sh.shape == (0, 1, 3)
    out = tmp_path / "empty2.ply"
    write_ply(g, out)
    assert plyfile.PlyData.read(str(out))["vertex"].count == 0
    assert summarize_ply(out)["count"] == 0


# --- round trips ------------------------------------------------------------------------------


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_activated(tmp_path, degree):
    g = random_gaussians(64, degree, seed=degree)
    path = tmp_path / "rt.ply"
    write_ply(g, path)
    back = read_ply(path)
    torch.testing.assert_close(back.means, g.means, rtol=0, atol=0)
    torch.testing.assert_close(back.sh, g.sh, rtol=0, atol=0)
    # log(s) stored as float32: off by <= half an ulp of |log s| < 8 (2^-22 = 2.4e-7), which exp
    # turns into a relative error, plus exp's own float32 rounding (2^-24 = 6e-8): <= 3.0e-7
    torch.testing.assert_close(back.scales, g.scales, rtol=3e-7, atol=0)
    torch.testing.assert_close(back.opacities, g.opacities, rtol=1e-6, atol=1e-7)
    torch.testing.assert_close(back.quats, g.quats, rtol=0, atol=2e-7)


def test_round_trip_stored_space(tmp_path):
    """read -> write reproduces the stored values up to the float32 rounding of the activated ones."""
    cols = stored_rows(50, 3, seed=5)
    src = tmp_path / "src.ply"
    write_with_plyfile(src, cols)
    out = tmp_path / "out.ply"
    write_ply(read_ply(src), out)
    a = plyfile.PlyData.read(str(src))["vertex"].data
    b = plyfile.PlyData.read(str(out))["vertex"].data
    for name in inria_names(3):
        if name.startswith(("x", "y", "z", "f_")):
            np.testing.assert_array_equal(b[name], a[name])
    for i in range(3):
        np.testing.assert_allclose(b[f"scale_{i}"], a[f"scale_{i}"], rtol=0, atol=1e-6)
    # d logit / d p = 1 / (p (1 - p)): one float32 ulp of p moves the logit by ulp / (p (1 - p)).
    p = 1 / (1 + np.exp(-a["opacity"].astype(np.float64)))
    tol = 2 * np.spacing(p.astype(np.float32)) / (p * (1 - p)) + 1e-6
    assert np.all(np.abs(b["opacity"] - a["opacity"]) <= tol)
    rots = np.stack([a[f"rot_{i}"] for i in range(4)], 1).astype(np.float64)
    rots /= np.linalg.norm(rots, axis=1, keepdims=True)
    np.testing.assert_allclose(np.stack([b[f"rot_{i}"] for i in range(4)], 1), rots, atol=2e-7)


def test_opacity_is_clamped_before_logit(tmp_path):
    g = random_gaussians(3, 0)
    g.opacities[:] = torch.tensor([0.0, 1.0, 0.5])
    path = tmp_path / "clamp.ply"
    write_ply(g, path)
    stored = plyfile.PlyData.read(str(path))["vertex"].data["opacity"]
    np.testing.assert_allclose(stored, [math.log(1e-7 / (1 - 1e-7)), math.log((1 - 1e-7) / 1e-7), 0.0], rtol=1e-6)
    assert np.all(np.isfinite(stored))


# --- bad input --------------------------------------------------------------------------------


def _assert_names_file(err: pytest.ExceptionInfo, path) -> str:
    msg = str(err.value)
    assert str(path) in msg and "\n" not in msg
    return msg


def test_missing_file(tmp_path):
    path = tmp_path / "nope.ply"
    with pytest.raises(DlaInputError) as err:
        read_ply(path)
    _assert_names_file(err, path)


def test_not_a_ply(tmp_path):
    path = tmp_path / "photo.ply"
    path.write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(200)))
    with pytest.raises(DlaInputError) as err:
        read_ply(path)
    _assert_names_file(err, path)


@pytest.mark.parametrize("fraction", [0.5, 0.97])
def test_truncated_binary(tmp_path, fraction):
    path = tmp_path / "cut.ply"
    write_ply(random_gaussians(20, 3), path)
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(DlaInputError) as err:
        read_ply(path)
    _assert_names_file(err, path)


@pytest.mark.parametrize("missing", ["x", "f_dc_1", "opacity", "scale_2", "rot_3"])
def test_missing_property(tmp_path, missing):
    cols = stored_rows(4, 0)
    del cols[missing]
    path = tmp_path / "missing.ply"
    write_with_plyfile(path, cols)
    with pytest.raises(DlaInputError) as err:
        read_ply(path)
    assert repr(missing) in _assert_names_file(err, path)


@pytest.mark.parametrize("name, value", [("y", np.nan), ("scale_0", np.inf), ("f_rest_4", -np.inf)])
def test_non_finite_values(tmp_path, name, value):
    cols = stored_rows(6, 1)
    cols[name][3] = value
    path = tmp_path / "nan.ply"
    write_with_plyfile(path, cols)
    with pytest.raises(DlaInputError) as err:
        read_ply(path)
    assert name in _assert_names_file(err, path)


@pytest.mark.parametrize("n_rest", [3, 5, 10, 44])
def test_bad_f_rest_count(tmp_path, n_rest):
    cols = stored_rows(3, 0)
    cols.update({f"f_rest_{i}": np.zeros(3) for i in range(n_rest)})
    path = tmp_path / "rest.ply"
    write_with_plyfile(path, cols)
    with pytest.raises(DlaInputError) as err:
        read_ply(path)
    assert "f_rest" in _assert_names_file(err, path)


def test_no_vertex_element(tmp_path):
    path = tmp_path / "faces.ply"
    arr = np.zeros(2, dtype=[("a", "<f4")])
    plyfile.PlyData([plyfile.PlyElement.describe(arr, "face_stuff")]).write(str(path))
    with pytest.raises(DlaInputError) as err:
        read_ply(path)
    assert "vertex" in _assert_names_file(err, path)


def test_zero_quaternion(tmp_path):
    cols = stored_rows(3, 0)
    for i in range(4):
        cols[f"rot_{i}"][1] = 0.0
    path = tmp_path / "zeroq.ply"
    write_with_plyfile(path, cols)
    with pytest.raises(DlaInputError) as err:
        read_ply(path)
    _assert_names_file(err, path)


# --- golden files (values documented in formats/gaussians-ply.md) ------------------------------


def test_golden_sh0(formats_dir):
    g = read_ply(formats_dir / "examples" / "gaussians_sh0.ply")
    assert len(g) == 3 and g.sh_degree == 0
    np.testing.assert_allclose(g.means.numpy(), [[0, 0, 0], [1, 0, 0], [0, 2, -0.5]])
    np.testing.assert_allclose(g.opacities.numpy(), [0.5, 0.75, 0.25], rtol=1e-6)
    np.testing.assert_allclose(g.scales.numpy(), [[0.01] * 3, [0.1, 0.02, 0.05], [0.2, 0.1, 0.1]], rtol=1e-6)
    s = math.sqrt(0.5)
    np.testing.assert_allclose(g.quats.numpy(), [[1, 0, 0, 0], [1, 0, 0, 0], [s, 0, 0, s]], atol=1e-7)
    np.testing.assert_allclose(g.rgb.numpy(), [[0.5, 0.5, 0.5], [1, 0, 0], [0, 0, 1]], atol=1e-6)


def test_golden_sh3(formats_dir):
    g = read_ply(formats_dir / "examples" / "gaussians_sh3.ply")
    assert len(g) == 2 and g.sh_degree == 3
    np.testing.assert_allclose(g.means.numpy(), [[0, 0, 1], [0.5, -0.5, 1]])
    np.testing.assert_allclose(g.opacities.numpy(), [0.75, 0.25], rtol=1e-6)
    np.testing.assert_allclose(g.scales.numpy(), np.full((2, 3), 0.03), rtol=1e-6)
    np.testing.assert_allclose(g.quats.numpy(), [[1, 0, 0, 0], [0, 1, 0, 0]])
    np.testing.assert_allclose(g.rgb.numpy(), [[0.5, 1, 0.5]] * 2, atol=1e-6)
    for i, sign in enumerate((1, -1)):
        for c in range(3):
            for k in range(1, 16):  # sh[i, k, c] = sign * (15 c + k) / 100
                assert g.sh[i, k, c].item() == pytest.approx(sign * (15 * c + k) / 100, rel=1e-6)


def test_summarize_golden(formats_dir):
    from dlacli.io.inspect import summarize

    path = formats_dir / "examples" / "gaussians_sh0.ply"
    summary = summarize(path)
    assert summary["kind"] == "gaussians.ply" and summary["format"] == "3dgs-ply (INRIA)"
    assert summary["count"] == 3 and summary["sh_degree"] == 0
    assert summary["bbox_min"] == pytest.approx([0, 0, -0.5]) and summary["bbox_max"] == pytest.approx([1, 2, 0])
    assert summary["opacity_mean"] == pytest.approx(0.5, rel=1e-6)
    assert summary["scale_median"] == pytest.approx(0.05, rel=1e-6)
    assert summary["encoding"] == "binary_little_endian" and summary["extra_properties"] == []
    import json

    json.dumps(summary)
