"""Gaussian PLY in the standard 3DGS layout (graphdeco ``save_ply``; read unchanged by gsplat, SuperSplat).

One ``vertex`` element, binary little-endian float32, properties in this order:
``x y z nx ny nz f_dc_0..2 f_rest_0..3(K-1)-1 opacity scale_0..2 rot_0..3`` where
- ``f_rest`` is channel-major: ``f_rest_{c*(K-1)+k}`` is band coefficient k of colour channel c;
- ``opacity`` is the logit, ``scale_*`` the log standard deviations, ``rot_*`` the quaternion w first;
- normals are written as zeros (graphdeco does the same).

Both directions avoid per-vertex Python loops: export views one [N, 62] float32 block as the record
dtype; import parses the ASCII header and ``np.frombuffer``s the payload (``plyfile`` falls back to a slow
per-element loop for non-mmappable streams such as uploads; docs/DECISIONS.md, "Numbers behind code comments").
Non-finite rows are counted and logged, never dropped.
"""

from __future__ import annotations

import logging
import math
import os
from pathlib import Path

import numpy as np
import torch
from torch import Tensor

from pipeline.splat.gaussians import check_gaussians

log = logging.getLogger(__name__)

_PLY_TYPES = {  # PLY scalar type name -> numpy little-endian dtype
    "char": "i1",
    "int8": "i1",
    "uchar": "u1",
    "uint8": "u1",
    "short": "<i2",
    "int16": "<i2",
    "ushort": "<u2",
    "uint16": "<u2",
    "int": "<i4",
    "int32": "<i4",
    "uint": "<u4",
    "uint32": "<u4",
    "float": "<f4",
    "float32": "<f4",
    "double": "<f8",
    "float64": "<f8",
}
_MAX_HEADER = 1 << 16  # a 3DGS header is ~1.5 KB; refuse to scan further for "end_header"


def ply_property_names(n_rest: int) -> list[str]:
    """Property names in file order for ``n_rest`` f_rest coefficients (45 for SH degree 3)."""
    return (
        ["x", "y", "z", "nx", "ny", "nz"]
        + [f"f_dc_{i}" for i in range(3)]
        + [f"f_rest_{i}" for i in range(n_rest)]
        + ["opacity"]
        + [f"scale_{i}" for i in range(3)]
        + [f"rot_{i}" for i in range(4)]
    )


def _count_nonfinite(table: np.ndarray, what: str) -> int:
    """Count rows of [N, F] with any NaN/Inf and log them (rows are kept)."""
    bad = int((~np.isfinite(table)).any(axis=1).sum())
    if bad:
        log.warning("%s: %d of %d Gaussians have non-finite values (kept as they are)", what, bad, len(table))
    return bad


def export_ply(params: dict[str, Tensor], path: str | os.PathLike[str] | None = None) -> bytes:
    """Serialise Gaussian parameters (``pipeline.splat.gaussians`` layout, raw/unactivated) to PLY bytes.

    If ``path`` is given the bytes are also written there (atomically: temp file, then rename).
    """
    n = check_gaussians(params)
    with torch.no_grad():
        shn = params["shN"].detach().float().cpu()  # [N, K-1, 3]
        cols = [
            params["means"].detach().float().cpu(),  # [N, 3]
            torch.zeros(n, 3),  # normals
            params["sh0"].detach().float().cpu().reshape(n, 3),  # [N, 3]
            shn.transpose(1, 2).reshape(n, -1),  # [N, 3*(K-1)], channel-major
            params["opacities"].detach().float().cpu().reshape(n, 1),
            params["scales"].detach().float().cpu(),
            params["quats"].detach().float().cpu(),
        ]
        table = np.ascontiguousarray(torch.cat(cols, dim=1).numpy(), dtype="<f4")  # [N, 62]
    names = ply_property_names(3 * shn.shape[1])
    _count_nonfinite(table, "export_ply")
    records = table.view(np.dtype([(name, "<f4") for name in names])).reshape(n)  # [N] structured, no copy
    header = "\n".join(
        ["ply", "format binary_little_endian 1.0", f"element vertex {n}"]
        + [f"property float {name}" for name in names]
        + ["end_header", ""]
    ).encode("ascii")
    data = header + records.tobytes()
    if path is not None:
        write_atomic(path, data)
    return data


def write_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary name beside it, so a reader never sees half a file (the
    PLY and SPZ writers)."""
    path = Path(path)
    tmp = path.with_name(path.name + ".tmp")
    tmp.write_bytes(data)
    os.replace(tmp, path)


def _parse_header(buf: bytes | memoryview) -> tuple[int, int, np.dtype]:
    """Return (payload offset, vertex count, record dtype). Only a single binary-LE vertex element."""
    end = bytes(buf[:_MAX_HEADER]).find(b"end_header")
    if not bytes(buf[:4]).startswith(b"ply") or end < 0:
        raise ValueError("not a PLY file (no 'ply' magic or no 'end_header' in the first 64 KiB)")
    nl = bytes(buf[end : end + 12]).find(b"\n")
    if nl < 0:
        raise ValueError("truncated PLY header")
    offset = end + nl + 1
    lines = bytes(buf[:end]).decode("ascii", errors="replace").splitlines()
    fmt, elements = None, []  # elements: [name, count, [(prop, dtype)]]
    for line in lines[1:]:
        words = line.split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "format":
            fmt = words[1] if len(words) > 1 else None
        elif words[0] == "element" and len(words) == 3:
            elements.append([words[1], int(words[2]), []])
        elif words[0] == "property" and elements:
            if words[1] == "list":
                raise ValueError(f"list property {words[-1]!r} is not supported in a Gaussian PLY")
            if words[1] not in _PLY_TYPES or len(words) != 3:
                raise ValueError(f"bad property line {line!r}")
            elements[-1][2].append((words[2], _PLY_TYPES[words[1]]))
        else:
            raise ValueError(f"unexpected PLY header line {line!r}")
    if fmt != "binary_little_endian":
        raise ValueError(f"only binary_little_endian PLY is supported, got format {fmt!r}")
    if len(elements) != 1 or elements[0][0] != "vertex":
        names = [e[0] for e in elements]
        raise ValueError(f"expected a single 'vertex' element (standard 3DGS PLY), got elements {names}")
    _, count, props = elements[0]
    return offset, count, np.dtype(props)


def read_ply(src: str | os.PathLike[str] | bytes | bytearray | memoryview) -> dict[str, Tensor]:
    """Read a 3DGS PLY (path or bytes) into the raw parameter layout of ``pipeline.splat.gaussians``.

    f_rest properties are ordered by their numeric suffix (as graphdeco's ``load_ply``), so files whose
    header lists them in another order still load correctly. Returns float32 CPU tensors.
    """
    buf = Path(src).read_bytes() if isinstance(src, (str, os.PathLike)) else src
    offset, n, dtype = _parse_header(buf)
    if len(buf) < offset + n * dtype.itemsize:
        raise ValueError(
            f"truncated PLY: {n} vertices need {n * dtype.itemsize} bytes after the header, "
            f"file has {len(buf) - offset}"
        )
    names = list(dtype.names or ())
    rest = sorted((nm for nm in names if nm.startswith("f_rest_")), key=lambda s: int(s.split("_")[-1]))
    k1 = len(rest) // 3
    if len(rest) % 3 or round(math.sqrt(k1 + 1)) ** 2 != k1 + 1:
        raise ValueError(f"{len(rest)} f_rest properties do not match any SH degree")
    keys = ["x", "y", "z"] + [f"f_dc_{i}" for i in range(3)] + rest + ["opacity"]
    keys += [f"scale_{i}" for i in range(3)] + [f"rot_{i}" for i in range(4)]
    missing = [k for k in keys if k not in dtype.fields]
    if missing:
        raise ValueError(f"PLY lacks 3DGS properties {missing}")
    if all(dtype.fields[nm][0] == np.dtype("<f4") for nm in names):  # the usual case: one float32 block
        flat = np.frombuffer(buf, dtype="<f4", count=n * len(names), offset=offset).reshape(n, len(names))
        table = flat[:, [names.index(k) for k in keys]]  # [N, F] one gather, in our column order
    else:  # mixed types: per-property conversion (no per-vertex loop either)
        rec = np.frombuffer(buf, dtype=dtype, count=n, offset=offset)
        table = np.stack([rec[k].astype(np.float32) for k in keys], axis=1)
    table = table.astype(np.float32, copy=False)
    _count_nonfinite(table, "read_ply")

    def part(a: int, b: int, shape: tuple[int, ...]) -> Tensor:  # columns [a, b) as a contiguous tensor
        return torch.from_numpy(np.ascontiguousarray(table[:, a:b]).reshape(shape))

    r = 6 + 3 * k1  # end of f_rest
    return {
        "means": part(0, 3, (n, 3)),
        "sh0": part(3, 6, (n, 1, 3)),
        "shN": part(6, r, (n, 3, k1)).transpose(1, 2).contiguous(),  # channel-major -> [N, K-1, 3]
        "opacities": part(r, r + 1, (n,)),
        "scales": part(r + 1, r + 4, (n, 3)),
        "quats": part(r + 4, r + 8, (n, 4)),
    }
