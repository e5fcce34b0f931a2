"""SPZ export (``pipeline.splat.spz``): the reference library's bytes, round-trip error bounds that follow from the
format's quantisation, degenerate Gaussians, and an independent reader (gsply).

Golden files in ``tests/splat/data`` (made once with the reference C++ library, nianticlabs/spz at 21715c3, built
locally; docs/DECISIONS.md, "Compact splat files"):
- ``spz_golden.ply``: 96 Gaussians of SH degree 3 in our PLY, 16 of them degenerate (scales beyond the stored
  range, opacity 0 / 1, coordinates near the 24-bit limit, colours and SH beyond what the format keeps, axis and
  sign-flipped quaternions);
- ``spz_golden_reference.spz``: the reference's ``loadSplatFromPly`` then ``saveSpz`` with
  ``PackOptions{version = 3, from = RDF}``;
- ``spz_golden_reference_decoded.ply``: the reference's ``loadSpz(to = RDF)`` of that file, then ``saveSplatToPly``;
- ``spz_golden_reference_v2.spz``: as ``spz_golden_reference.spz`` with ``version = 2``.
"""

from __future__ import annotations

import gzip
import logging
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from pipeline.splat.ply import export_ply, read_ply
from pipeline.splat.spz import COLOR_SCALE, export_spz, read_spz, spz_header

DATA = Path(__file__).parent / "data"

# Worst-case round-trip errors, from the quantisation (module docstring of pipeline.splat.spz).
POS_ERR = 0.5 / 4096  # 12 fractional bits, rounded
LOG_SCALE_ERR = 0.5 / 16  # u8 of (log sigma + 10) * 16
SCALE_RANGE = (-10.0, 255 / 16 - 10)  # what the u8 reaches; beyond it the value is clamped
ALPHA_ERR = 0.5 / 255 + 1e-6  # + float32 rounding of the decoded logit's sigmoid
DC_ERR = 0.5 / (COLOR_SCALE * 255) + 1e-6  # (0 itself is a half-code case: 127.5 rounds up to 128)
DC_RANGE = 127.5 / (COLOR_SCALE * 255)  # |sh0| the u8 reaches (colour 0.5 +- 0.94)
SH1_ERR, SH_REST_ERR = 4.5 / 128, 8.5 / 128  # 1/128 steps rounded, then snapped to buckets of 8 and 16 codes
# Rotation: the three smallest components are each within h = (1/sqrt 2) / 511 / 2 = 6.9e-4; the largest, derived
# as sqrt(1 - sum q_i^2), moves by sum |q_i| h / q_max <= 3h. So |dq|^2 <= 3h^2 + 9h^2 and the angle, 2 |dq| at
# most, is within 2 sqrt(12) h = 4.8e-3 rad (0.27 degrees).
ROT_ANGLE_ERR = 2 * math.sqrt(12) * (math.sqrt(0.5) / 511 / 2) + 1e-5
F32 = 2e-7  # float32 rounding of values of order 1


def _gaussians(n: int, degree: int, seed: int) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    return {
        "means": torch.randn(n, 3, generator=g) * 5,
        "scales": torch.rand(n, 3, generator=g) * 12 - 9.5,  # inside the stored range
        "quats": torch.randn(n, 4, generator=g),
        "opacities": torch.randn(n, generator=g) * 3,
        "sh0": torch.randn(n, 1, 3, generator=g),
        "shN": (torch.rand(n, (degree + 1) ** 2 - 1, 3, generator=g) * 2 - 1),  # inside [-1, 1]
    }


def _angle(q1: torch.Tensor, q2: torch.Tensor) -> torch.Tensor:
    """Rotation angle between quaternions [N, 4] (any norm, q and -q the same rotation)."""
    d = (torch.nn.functional.normalize(q1.double(), dim=1) * torch.nn.functional.normalize(q2.double(), dim=1))
    return 2 * torch.acos(d.sum(1).abs().clamp(max=1.0))


def _assert_within_bounds(p: dict[str, torch.Tensor], r: dict[str, torch.Tensor]) -> None:
    assert {k: tuple(v.shape) for k, v in r.items()} == {k: tuple(v.shape) for k, v in p.items()}
    assert all(v.dtype == torch.float32 and torch.isfinite(v).all() for v in r.values())
    reach = p["means"].abs().max().item()
    assert (r["means"] - p["means"]).abs().max() <= POS_ERR + reach * 1e-7
    want_scales = p["scales"].clamp(*SCALE_RANGE)
    assert (r["scales"] - want_scales).abs().max() <= LOG_SCALE_ERR + F32 * 10
    assert _angle(r["quats"], p["quats"]).max() <= ROT_ANGLE_ERR
    assert (torch.sigmoid(r["opacities"]) - torch.sigmoid(p["opacities"])).abs().max() <= ALPHA_ERR
    want_dc = p["sh0"].clamp(-DC_RANGE, DC_RANGE)
    assert (r["sh0"] - want_dc).abs().max() <= DC_ERR + F32 * 4
    if p["shN"].shape[1]:
        want = p["shN"].clamp(-1.0, 127 / 128)
        assert (r["shN"][:, :3] - want[:, :3]).abs().max() <= SH1_ERR + F32
    if p["shN"].shape[1] > 3:
        assert (r["shN"][:, 3:] - want[:, 3:]).abs().max() <= SH_REST_ERR + F32


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_within_the_quantisation_bounds(degree):
    p = _gaussians(5000, degree, seed=degree)
    data = export_spz(p)
    assert spz_header(data) == {"version": 3, "num_points": 5000, "sh_degree": degree, "fractional_bits": 12,
                                "flags": 0}
    r = read_spz(data)
    _assert_within_bounds(p, r)
    # the bounds are tight: the largest errors come close to them (a looser coder would not)
    assert (r["means"] - p["means"]).abs().max() > 0.9 * POS_ERR
    assert (r["scales"] - p["scales"]).abs().max() > 0.9 * LOG_SCALE_ERR
    assert _angle(r["quats"], p["quats"]).max() > 0.3 * ROT_ANGLE_ERR
    # a second trip changes nothing: decoded values are exactly representable
    again = read_spz(export_spz(r))
    assert all(torch.equal(again[k], r[k]) for k in ("means", "scales", "sh0", "shN"))
    assert _angle(again["quats"], r["quats"]).max() <= ROT_ANGLE_ERR  # the derived largest is not on the grid
    assert export_spz(p) == data  # deterministic bytes (gzip mtime 0)


def test_our_payload_is_the_reference_librarys_byte_for_byte():
    """Our writer against the reference's ``saveSpz`` on the same PLY, including the degenerate rows."""
    ours = gzip.decompress(export_spz(read_ply(DATA / "spz_golden.ply")))
    ref = gzip.decompress((DATA / "spz_golden_reference.spz").read_bytes())
    assert len(ours) == len(ref) == 16 + 96 * (9 + 1 + 3 + 3 + 4 + 45)
    assert ours == ref


def test_version_2_for_older_readers_is_the_reference_librarys_too():
    """Version 2 (x, y, z of the quaternion in 8 bits, w derived), for readers that stop there."""
    golden = read_ply(DATA / "spz_golden.ply")
    data = export_spz(golden, version=2)
    ref = (DATA / "spz_golden_reference_v2.spz").read_bytes()
    assert spz_header(data)["version"] == 2
    assert gzip.decompress(data) == gzip.decompress(ref)
    assert len(gzip.decompress(ref)) == 16 + 96 * (9 + 1 + 3 + 3 + 3 + 45)
    r2, r3 = read_spz(ref), read_spz(DATA / "spz_golden_reference.spz")
    for k in ("means", "scales", "opacities", "sh0", "shN"):  # only the rotations are stored differently
        assert torch.equal(r2[k], r3[k]), k
    # 8 bits for x, y, z are coarser: the median rotation error of random Gaussians is several times version 3's
    p = _gaussians(4000, 0, seed=11)
    e2 = _angle(read_spz(export_spz(p, version=2))["quats"], p["quats"]).median()
    e3 = _angle(read_spz(export_spz(p))["quats"], p["quats"]).median()
    assert e2 > 3 * e3
    with pytest.raises(ValueError, match="version 4"):
        export_spz(p, version=4)


def test_our_reader_decodes_as_the_reference_does():
    ref = read_ply(DATA / "spz_golden_reference_decoded.ply")  # the reference's loadSpz(to=RDF)
    ours = read_spz(DATA / "spz_golden_reference.spz")
    for k in ("means", "scales", "sh0", "shN"):
        assert (ours[k] - ref[k]).abs().max() <= 1e-6, k
    assert _angle(ours["quats"], ref["quats"]).max() < 1e-3
    # opacity codes 0 and 255: the reference decodes +-inf, we decode the logit of half a code inside
    inf = ~torch.isfinite(ref["opacities"])
    assert int(inf.sum()) >= 2 and torch.isfinite(ours["opacities"]).all()
    assert (ours["opacities"][~inf] - ref["opacities"][~inf]).abs().max() <= 1e-5
    assert (torch.sigmoid(ours["opacities"][inf]) - torch.sigmoid(ref["opacities"][inf])).abs().max() <= ALPHA_ERR
    _assert_within_bounds(read_ply(DATA / "spz_golden.ply"), ours)


def test_degenerate_gaussians():
    n = 8
    p = _gaussians(n, 3, seed=7)
    p["scales"][0] = torch.tensor([-40.0, 30.0, 0.0])  # tiny and huge: clamped to the stored range
    p["opacities"][:2] = torch.tensor([-1e4, 1e4])  # opacity 0 and 1
    p["quats"][2] = 0.0  # no rotation at all: written as the identity
    p["quats"][3] = torch.tensor([0.0, 0.0, 0.0, -3.0])  # largest component negative, unnormalised
    p["sh0"][4] = torch.tensor([[50.0, -50.0, 0.0]])
    p["shN"][5] = 9.0
    r = read_spz(export_spz(p))
    assert r["scales"][0].tolist() == pytest.approx([-10.0, SCALE_RANGE[1], 0.0], abs=LOG_SCALE_ERR)
    assert torch.sigmoid(r["opacities"][:2]).tolist() == pytest.approx([0.0, 1.0], abs=ALPHA_ERR)
    assert torch.isfinite(r["opacities"]).all()
    assert r["quats"][2].tolist() == pytest.approx([1.0, 0.0, 0.0, 0.0], abs=1e-6)
    assert _angle(r["quats"][3:4], p["quats"][3:4]).item() < 1e-6  # an axis rotation is exact
    assert r["sh0"][4, 0].tolist() == pytest.approx([DC_RANGE, -DC_RANGE, 0.0], abs=DC_ERR)
    # clamped on disk (RUB) to the codes' range [-1, 127/128]; the coefficients that change sign come back as 1
    assert set(r["shN"][5].flatten().tolist()) == {127 / 128, 1.0}


def test_far_positions_take_fewer_fractional_bits_instead_of_wrapping(caplog):
    """The reference always writes 12 fractional bits and wraps coordinates beyond +-2048; the header field
    lets us keep them (every reader takes the bits from the header)."""
    p = _gaussians(100, 1, seed=3)
    p["means"][0] = torch.tensor([30000.0, -5.0, 0.25])
    data = export_spz(p)
    fb = spz_header(data)["fractional_bits"]
    assert fb == 8  # 30000 * 2^8 < 2^23 <= 30000 * 2^9
    r = read_spz(data)
    assert (r["means"] - p["means"]).abs().max() <= 0.5 / 2**fb + 30000 * 1e-7
    with caplog.at_level(logging.WARNING, logger="pipeline.splat.spz"):
        p["means"][1] = torch.tensor([1e9, 0.0, 0.0])  # beyond even 0 fractional bits: clamped, and said
        r = read_spz(export_spz(p))
    assert r["means"][1, 0].item() == 2**23 - 1 and "clamped" in caplog.text


def test_non_finite_values_are_counted_and_written_as_zero(caplog):
    p = _gaussians(10, 0, seed=4)
    p["means"][1, 2] = float("nan")
    p["opacities"][2] = float("inf")
    with caplog.at_level(logging.WARNING, logger="pipeline.splat.spz"):
        r = read_spz(export_spz(p))
    assert "2 of 10 Gaussians have non-finite values" in caplog.text
    assert r["means"][1, 2].item() == 0.0 and torch.sigmoid(r["opacities"][2]).item() == pytest.approx(0.5, abs=0.01)


def test_bad_files_are_refused():
    good = export_spz(_gaussians(10, 1, seed=5))
    with pytest.raises(ValueError, match="no gzip magic"):
        read_spz(b"ply\nformat binary_little_endian 1.0\n")
    with pytest.raises(ValueError, match="version 4"):
        read_spz(b"NGSP" + bytes(28))
    with pytest.raises(ValueError, match="truncated SPZ"):
        read_spz(gzip.compress(gzip.decompress(good)[:-5]))
    body = bytearray(gzip.decompress(good))
    body[0] = 0
    with pytest.raises(ValueError, match="magic"):
        read_spz(gzip.compress(bytes(body)))
    with pytest.raises(ValueError, match="SH degree 0..3"):
        export_spz(_gaussians(10, 0, seed=5) | {"shN": torch.zeros(10, 24, 3)})


def test_the_frame_is_rub_on_disk_and_ours_after_reading():
    """SPZ stores RUB (x right, y up, z back); our PLY is RDF: y and z of a position change sign on disk."""
    p = _gaussians(1, 0, seed=6)
    p["means"][0] = torch.tensor([1.0, 2.0, 3.0])
    body = gzip.decompress(export_spz(p))
    fixed = np.frombuffer(body[16:25], dtype=np.uint8).reshape(3, 3).astype(np.int64)
    value = fixed[:, 0] | (fixed[:, 1] << 8) | (fixed[:, 2] << 16)
    value = np.where(value >= 1 << 23, value - (1 << 24), value)
    assert value.tolist() == [4096, -8192, -12288]
    assert read_spz(export_spz(p))["means"][0].tolist() == [1.0, 2.0, 3.0]


def test_an_independent_reader_agrees(tmp_path):
    """gsply (PyPI, MIT) reads SPZ with its own decoder and no change of axes: it must see our file in RUB."""
    import gsply.spz as gsply_spz  # the dev extra has it
    p = _gaussians(2000, 3, seed=8)
    export_spz(p, tmp_path / "x.spz")
    ours = read_spz(tmp_path / "x.spz")
    theirs = gsply_spz.read_spz(tmp_path / "x.spz")
    turn = torch.tensor([1.0, -1.0, -1.0])
    signs = torch.tensor([-1, -1, 1, -1, 1, 1, -1, 1, -1, 1, -1, -1, 1, -1, 1.0])[:, None]
    assert np.abs(np.asarray(theirs.means) - (ours["means"] * turn).numpy()).max() <= 1e-6
    assert np.abs(np.asarray(theirs.scales) - ours["scales"].numpy()).max() <= 1e-6
    q = torch.from_numpy(np.asarray(theirs.quats, dtype=np.float32)) * torch.tensor([1.0, 1.0, -1.0, -1.0])
    assert _angle(q, ours["quats"]).max() < 1e-3
    alpha = 1 / (1 + np.exp(-np.asarray(theirs.opacities, dtype=np.float64)))
    assert np.abs(alpha - torch.sigmoid(ours["opacities"].double()).numpy()).max() <= ALPHA_ERR
    assert np.abs(np.asarray(theirs.sh0).reshape(-1, 1, 3) - ours["sh0"].numpy()).max() <= 1e-6
    assert np.abs(np.asarray(theirs.shN) - (ours["shN"] * signs).numpy()).max() <= 1e-6


def test_a_ply_file_and_its_spz(tmp_path):
    """The PLY-Gaussians -> SPZ -> Gaussians path through files, as the export stage writes them."""
    p = _gaussians(3000, 3, seed=9)
    export_ply(p, tmp_path / "r.ply")
    data = export_spz(read_ply(tmp_path / "r.ply"), tmp_path / "r.spz")
    assert (tmp_path / "r.spz").read_bytes() == data and not list(tmp_path.glob("*.tmp"))
    _assert_within_bounds(p, read_spz(tmp_path / "r.spz"))
    ratio = (tmp_path / "r.ply").stat().st_size / len(data)
    assert ratio > 4.0  # random coefficients compress least; a trained scene does better (tests/evaluate)
