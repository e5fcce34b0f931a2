"""3DGS PLY: exact round trip, graphdeco-style read with plain plyfile, header order, NaN counting."""

from __future__ import annotations

import io
import logging

import numpy as np
import pytest
import torch
from plyfile import PlyData, PlyElement

from pipeline.splat.gaussians import GAUSSIAN_KEYS
from pipeline.splat.ply import export_ply, ply_property_names, read_ply


def random_params(n: int, degree: int, seed: int = 0) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    k1 = (degree + 1) ** 2 - 1
    return {
        "means": torch.randn(n, 3, generator=g),
        "scales": torch.randn(n, 3, generator=g) - 3,
        "quats": torch.randn(n, 4, generator=g),
        "opacities": torch.randn(n, generator=g),
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": torch.randn(n, k1, 3, generator=g),
    }


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_round_trip_exact(tmp_path, degree):
    params = random_params(257, degree)
    path = tmp_path / "g.ply"
    data = export_ply(params, path)
    assert path.read_bytes() == data
    header = data[: data.index(b"end_header")].decode()
    assert "format binary_little_endian 1.0" in header and "element vertex 257" in header
    payload = len(data) - (data.index(b"end_header") + len(b"end_header\n"))
    assert payload == 257 * (17 + 3 * ((degree + 1) ** 2 - 1)) * 4  # 62 floats per Gaussian at degree 3
    for got in (read_ply(path), read_ply(data), read_ply(memoryview(data))):
        for k in GAUSSIAN_KEYS:
            assert got[k].dtype == torch.float32
            assert torch.equal(got[k], params[k]), k


def test_channel_major_f_rest_layout():
    params = random_params(4, 3)
    rec = PlyData.read(io.BytesIO(export_ply(params)))["vertex"]
    # f_rest_{c*15 + k} is band coefficient k of colour channel c
    for c in range(3):
        for k in (0, 7, 14):
            np.testing.assert_array_equal(rec[f"f_rest_{c * 15 + k}"], params["shN"][:, k, c].numpy())
    assert [p.name for p in rec.properties] == ply_property_names(45)


def _by_index(names: list[str]) -> list[str]:
    return sorted(names, key=lambda x: int(x.split("_")[-1]))


def graphdeco_load_ply(path, max_sh_degree: int = 3) -> dict[str, np.ndarray]:
    """graphdeco-inria/gaussian-splatting ``GaussianModel.load_ply``, minus the torch/CUDA wrapping."""
    plydata = PlyData.read(path)
    el = plydata.elements[0]
    xyz = np.stack((np.asarray(el["x"]), np.asarray(el["y"]), np.asarray(el["z"])), axis=1)
    opacities = np.asarray(el["opacity"])[..., np.newaxis]
    features_dc = np.zeros((xyz.shape[0], 3, 1))
    features_dc[:, 0, 0] = np.asarray(el["f_dc_0"])
    features_dc[:, 1, 0] = np.asarray(el["f_dc_1"])
    features_dc[:, 2, 0] = np.asarray(el["f_dc_2"])
    extra_f_names = [p.name for p in el.properties if p.name.startswith("f_rest_")]
    extra_f_names = sorted(extra_f_names, key=lambda x: int(x.split("_")[-1]))
    assert len(extra_f_names) == 3 * (max_sh_degree + 1) ** 2 - 3
    features_extra = np.zeros((xyz.shape[0], len(extra_f_names)))
    for idx, attr_name in enumerate(extra_f_names):
        features_extra[:, idx] = np.asarray(el[attr_name])
    features_extra = features_extra.reshape((features_extra.shape[0], 3, (max_sh_degree + 1) ** 2 - 1))
    scale_names = _by_index([p.name for p in el.properties if p.name.startswith("scale_")])
    scales = np.zeros((xyz.shape[0], len(scale_names)))
    for idx, attr_name in enumerate(scale_names):
        scales[:, idx] = np.asarray(el[attr_name])
    rot_names = _by_index([p.name for p in el.properties if p.name.startswith("rot")])
    rots = np.zeros((xyz.shape[0], len(rot_names)))
    for idx, attr_name in enumerate(rot_names):
        rots[:, idx] = np.asarray(el[attr_name])
    return {
        "xyz": xyz,
        "features_dc": features_dc.transpose(0, 2, 1),  # graphdeco: .transpose(1, 2) on a [N, 3, 1] tensor
        "features_rest": features_extra.transpose(0, 2, 1),
        "opacity": opacities,
        "scaling": scales,
        "rotation": rots,
    }


def test_graphdeco_style_read(tmp_path):
    params = random_params(100, 3, seed=5)
    export_ply(params, tmp_path / "point_cloud.ply")
    g = graphdeco_load_ply(tmp_path / "point_cloud.ply")
    np.testing.assert_array_equal(g["xyz"], params["means"].numpy())
    np.testing.assert_array_equal(g["features_dc"], params["sh0"].numpy())
    np.testing.assert_array_equal(g["features_rest"], params["shN"].numpy())
    np.testing.assert_array_equal(g["opacity"][:, 0], params["opacities"].numpy())
    np.testing.assert_array_equal(g["scaling"], params["scales"].numpy())
    np.testing.assert_array_equal(g["rotation"], params["quats"].numpy())  # w first


def test_reads_other_property_order_and_extra_props(tmp_path):
    """A writer that orders f_rest differently, adds properties or uses doubles still loads by name."""
    params = random_params(20, 1, seed=2)
    names = ply_property_names(9)
    table = np.concatenate(
        [
            params["means"],
            torch.zeros(20, 3),
            params["sh0"][:, 0],
            params["shN"].transpose(1, 2).reshape(20, 9),
            params["opacities"][:, None],
            params["scales"],
            params["quats"],
        ],
        axis=1,
    )
    order = list(reversed(range(len(names))))
    dtype = [(names[i], "<f8" if names[i].startswith("rot") else "<f4") for i in order] + [("red", "u1")]
    arr = np.zeros(20, dtype=dtype)
    for i in order:
        arr[names[i]] = table[:, i]
    PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(tmp_path / "odd.ply"))
    got = read_ply(tmp_path / "odd.ply")
    for k in GAUSSIAN_KEYS:
        assert torch.equal(got[k], params[k]), k


def test_nonfinite_rows_counted_and_kept(tmp_path, caplog):
    params = random_params(10, 0)
    params["means"][3, 1] = float("nan")
    params["scales"][7, 0] = float("inf")
    with caplog.at_level(logging.WARNING, logger="pipeline.splat.ply"):
        data = export_ply(params)
        got = read_ply(data)
    assert sum("2 of 10 Gaussians have non-finite values" in r.message for r in caplog.records) == 2
    assert got["means"].shape == (10, 3)
    assert torch.isnan(got["means"][3, 1]) and torch.isinf(got["scales"][7, 0])


def test_rejects_non_3dgs_files(tmp_path):
    arr = np.zeros(3, dtype=[("x", "<f4"), ("y", "<f4"), ("z", "<f4")])
    PlyData([PlyElement.describe(arr, "vertex")], text=True).write(str(tmp_path / "a.ply"))
    with pytest.raises(ValueError, match="binary_little_endian"):
        read_ply(tmp_path / "a.ply")
    PlyData([PlyElement.describe(arr, "vertex")], byte_order="<").write(str(tmp_path / "b.ply"))
    with pytest.raises(ValueError, match="lacks 3DGS properties"):
        read_ply(tmp_path / "b.ply")
    with pytest.raises(ValueError, match="truncated"):
        read_ply(export_ply(random_params(5, 0))[:-4])
    with pytest.raises(ValueError, match="not a PLY"):
        read_ply(b"hello")
