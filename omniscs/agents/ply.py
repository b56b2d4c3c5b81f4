"""The standard 3D Gaussian splatting PLY file (the original 3DGS code's, Trellis' and other image-to-3D
generators', every splat viewer's), read into and written from ``GaussianParams``.

Layout: one ``vertex`` element with float properties x y z, nx ny nz (zeros), f_dc_0..2, f_rest_0..f_rest_{3(K-1)-1}
(channel-major: f_rest_{c(K-1)+k} = sh_rest[:, k, c]), opacity (logit), scale_0..2 (log metres), rot_0..3 (w, x, y, z,
unnormalised). The 3DGS conventions are the project's, so values pass through unchanged. The writer writes exactly
that (binary_little_endian, float32); the reader finds properties by name, in any order and of any scalar type, in
binary (either byte order) or ascii files whose first element is ``vertex``; other properties and elements are ignored.
The SH degree follows from the number of f_rest properties (0, 9, 24, 45 -> 0..3).
"""
from __future__ import annotations

import io
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np
import torch

from omniscs.errors import ValidationError
from omniscs.gaussians import GaussianParams
from omniscs.render.sh import MAX_SH_DEGREE, num_sh_bases
from omniscs.storage import atomic_write_bytes

#: PLY scalar type names (with their aliases) -> numpy type code (the byte order comes from the file's format).
PLY_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
             "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
             "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}

#: PLY format -> numpy byte order (None: ascii).
PLY_FORMATS = {"binary_little_endian": "<", "binary_big_endian": ">", "ascii": None}

#: Number of f_rest properties -> SH degree.
DEGREE_OF_REST_COUNT = {3 * (num_sh_bases(d) - 1): d for d in range(MAX_SH_DEGREE + 1)}

#: Properties every Gaussian PLY file must have, in the order the reader stacks them.
REQUIRED_PROPERTIES = ("x", "y", "z", "f_dc_0", "f_dc_1", "f_dc_2", "opacity", "scale_0", "scale_1", "scale_2",
                       "rot_0", "rot_1", "rot_2", "rot_3")

#: A header line longer than this, or a header with more lines, is not a PLY header.
MAX_HEADER_LINE_BYTES = 4096
MAX_HEADER_LINES = 10_000


@dataclass(frozen=True)
class PlyHeader:
    """What a reader needs of a PLY header: the format and the (first) vertex element's scalar properties."""

    format: str                          # ascii | binary_little_endian | binary_big_endian
    vertex_count: int
    properties: list[tuple[str, str]]    # (name, numpy type code), in file order

    @property
    def names(self) -> list[str]:
        return [name for name, _ in self.properties]


def gaussian_ply_properties(sh_degree: int) -> list[str]:
    """Vertex property names of a 3DGS PLY file of ``sh_degree``, in the order the original code writes them."""
    n_rest = 3 * (num_sh_bases(sh_degree) - 1)
    return ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *(f"f_rest_{i}" for i in range(n_rest)),
            "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]


def write_gaussian_ply(params: GaussianParams, path: str | os.PathLike) -> Path:
    """Write ``params`` as a 3DGS PLY file (binary_little_endian, float32), atomically; returns the path."""
    path = Path(path)
    degree = params.sh_degree
    if tuple(params.sh_rest.shape[1:]) != (num_sh_bases(degree) - 1, 3):
        raise ValidationError(f"cannot write {path}: sh_rest has shape {tuple(params.sh_rest.shape)}, "
                              f"not [N, (degree+1)^2 - 1, 3]")
    table = _vertex_table(params)
    bad = ~np.isfinite(table).all(1)
    if bad.any():
        raise ValidationError(f"cannot write {path}: {int(bad.sum())} of {len(table)} Gaussians have non-finite "
                              f"parameters (first: index {int(np.flatnonzero(bad)[0])})")
    header = "".join(["ply\nformat binary_little_endian 1.0\n", f"element vertex {len(table)}\n",
                      *(f"property float {name}\n" for name in gaussian_ply_properties(degree)), "end_header\n"])
    return atomic_write_bytes(path, header.encode("ascii") + table.astype("<f4").tobytes())


def read_gaussian_ply(path: str | os.PathLike) -> GaussianParams:
    """The Gaussians of a 3DGS PLY file as float32 parameters on the CPU; a clear error for anything malformed."""
    path = Path(path)
    with _open(path) as fh:
        header = read_ply_header(fh, path)
        rest_names = _rest_properties(path, header.names)
        columns = _vertex_columns(path, header, fh.read())
    values = _stack(columns, [*REQUIRED_PROPERTIES, *rest_names])  # [N, 14 + 3 (K-1)]
    bad = ~np.isfinite(values).all(1)
    if bad.any():
        raise ValidationError(f"{path}: {int(bad.sum())} of {len(values)} Gaussians have non-finite values "
                              f"(NaN, Inf or beyond float32; first: vertex {int(np.flatnonzero(bad)[0])})")
    n, k1, first = len(values), len(rest_names) // 3, len(REQUIRED_PROPERTIES)
    sh_rest = values[:, first:].reshape(n, 3, k1).transpose(0, 2, 1)  # channel-major -> [N, K-1, 3]

    def tensor(a: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(a, dtype=np.float32))

    return GaussianParams(means=tensor(values[:, 0:3]), quats=tensor(values[:, 10:14]),
                          log_scales=tensor(values[:, 7:10]), opacity_logits=tensor(values[:, 6]),
                          sh_dc=tensor(values[:, 3:6]), sh_rest=tensor(sh_rest))


def ply_header_properties(path: str | os.PathLike) -> tuple[str, list[str], int]:
    """(format, vertex property names in file order, vertex count) of a PLY file; the body is not read."""
    path = Path(path)
    with _open(path) as fh:
        header = read_ply_header(fh, path)
    return header.format, header.names, header.vertex_count


def read_ply_header(fh: BinaryIO, path: Path) -> PlyHeader:
    """Parse the header at the start of ``fh``, leaving ``fh`` at the first body byte."""
    if fh.readline(MAX_HEADER_LINE_BYTES).rstrip(b"\r\n") != b"ply":
        raise ValidationError(f"{path}: not a PLY file (it does not start with a 'ply' line)")
    fmt, elements = None, []  # elements: (name, count, [(property name, type code or "list")])
    for _ in range(MAX_HEADER_LINES):
        line = fh.readline(MAX_HEADER_LINE_BYTES)
        if not line:
            raise ValidationError(f"{path}: PLY header ends without an end_header line")
        words = line.decode("ascii", errors="replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            return _vertex_header(path, fmt, elements)
        if words[0] == "format":
            if len(words) != 3 or words[1] not in PLY_FORMATS:
                raise ValidationError(f"{path}: unknown PLY format line {' '.join(words)!r}")
            fmt = words[1]
        elif words[0] == "element" and len(words) == 3 and words[2].isdigit():
            elements.append((words[1], int(words[2]), []))
        elif words[0] == "property" and elements and len(words) in (3, 5):
            _add_property(path, elements[-1], words)
        else:
            raise ValidationError(f"{path}: unexpected PLY header line {line.decode('ascii', 'replace').strip()!r}")
    raise ValidationError(f"{path}: PLY header has more than {MAX_HEADER_LINES} lines without end_header")


def _open(path: Path) -> BinaryIO:
    try:
        return open(path, "rb")
    except FileNotFoundError:
        raise ValidationError(f"{path}: no such file") from None


def _add_property(path: Path, element: tuple[str, int, list], words: list[str]) -> None:
    name, _, properties = element
    if words[1] == "list":
        if name == "vertex":
            raise ValidationError(f"{path}: vertex property {words[-1]!r} is a list; Gaussians have scalars only")
        properties.append((words[-1], "list"))
        return
    if words[1] not in PLY_TYPES and name == "vertex":
        raise ValidationError(f"{path}: vertex property {words[2]!r} has unknown PLY type {words[1]!r}")
    if len(words) != 3:
        raise ValidationError(f"{path}: malformed PLY property line {' '.join(words)!r}")
    properties.append((words[2], PLY_TYPES.get(words[1], "?")))


def _vertex_header(path: Path, fmt: str | None, elements: list) -> PlyHeader:
    if fmt is None:
        raise ValidationError(f"{path}: PLY header has no format line")
    names = [name for name, _, _ in elements]
    if "vertex" not in names:
        raise ValidationError(f"{path}: PLY file has no vertex element")
    if names[0] != "vertex":
        raise ValidationError(f"{path}: the vertex element must be the first element (the file has {names})")
    _, count, properties = elements[0]
    seen = [name for name, _ in properties]
    duplicates = sorted({name for name in seen if seen.count(name) > 1})
    if duplicates:
        raise ValidationError(f"{path}: vertex properties named more than once: {', '.join(duplicates)}")
    return PlyHeader(fmt, count, properties)


def _rest_properties(path: Path, names: list[str]) -> list[str]:
    """The f_rest property names in coefficient order (checks the required properties and the SH degree)."""
    missing = [name for name in REQUIRED_PROPERTIES if name not in names]
    if missing:
        raise ValidationError(f"{path}: vertex element lacks the Gaussian properties {', '.join(missing)}")
    count = sum(name.startswith("f_rest_") for name in names)
    if count not in DEGREE_OF_REST_COUNT:
        raise ValidationError(f"{path}: {count} f_rest properties; a Gaussian PLY file has 0, 9, 24 or 45 "
                              f"(SH degree 0 to 3)")
    expected = [f"f_rest_{i}" for i in range(count)]
    if not set(expected) <= set(names):
        raise ValidationError(f"{path}: the f_rest properties are not numbered f_rest_0 to f_rest_{count - 1}")
    return expected


def _vertex_columns(path: Path, header: PlyHeader, body: bytes) -> dict[str, np.ndarray]:
    """Vertex property name -> [N] values of the body (binary or ascii)."""
    n, names = header.vertex_count, header.names
    order = PLY_FORMATS[header.format]
    if order is not None:
        dtype = np.dtype([(name, order + code) for name, code in header.properties])
        if len(body) < n * dtype.itemsize:
            raise ValidationError(f"{path}: truncated body: {n} vertices need {n * dtype.itemsize} bytes, "
                                  f"the file has {len(body)}")
        table = np.frombuffer(body, dtype, count=n)
        return {name: table[name] for name in names}
    table = _ascii_table(path, body, n, len(names))
    return {name: table[:, i] for i, name in enumerate(names)}


def _ascii_table(path: Path, body: bytes, n: int, width: int) -> np.ndarray:  # -> [n, width] float64
    if n == 0:
        return np.zeros((0, width))
    try:
        with warnings.catch_warnings():  # blank lines, no data at all: the shape check below reports
            warnings.simplefilter("ignore", UserWarning)
            table = np.loadtxt(io.StringIO(body.decode("ascii")), dtype=np.float64, max_rows=n, ndmin=2,
                               comments=None)
    except (ValueError, UnicodeDecodeError) as e:
        raise ValidationError(f"{path}: malformed ascii vertex rows ({str(e).split('; use')[0]})") from None
    if table.shape[0] < n:
        raise ValidationError(f"{path}: truncated ascii body: {table.shape[0]} of {n} vertex rows")
    if table.shape[1] != width:
        raise ValidationError(f"{path}: ascii vertex rows have {table.shape[1]} values; the header lists {width} "
                              f"properties")
    return table


def _stack(columns: dict[str, np.ndarray], names: list[str]) -> np.ndarray:  # -> [N, len(names)] float32
    with np.errstate(over="ignore", invalid="ignore"):  # out-of-range doubles become Inf: reported by the caller
        return np.stack([columns[name].astype(np.float32) for name in names], 1)


def _vertex_table(params: GaussianParams) -> np.ndarray:  # -> [N, P] float32 in gaussian_ply_properties order
    def cpu(t: torch.Tensor) -> torch.Tensor:
        return t.detach().to("cpu", torch.float32)

    n = len(params)
    rest = cpu(params.sh_rest).transpose(1, 2).reshape(n, 3 * params.sh_rest.shape[1])  # channel-major
    parts = [cpu(params.means), torch.zeros(n, 3), cpu(params.sh_dc), rest, cpu(params.opacity_logits)[:, None],
             cpu(params.log_scales), cpu(params.quats)]
    return torch.cat(parts, 1).numpy()
