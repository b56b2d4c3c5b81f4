"""The 3DGS PLY file: written exactly as the original code writes it, read back bit for bit, read by name whatever
the order, type, byte order or encoding another tool chose, and every malformed file is a clear ValidationError."""
from __future__ import annotations

import re

import numpy as np
import pytest
import torch

from omniscs.agents.ply import ply_header_properties, read_gaussian_ply, write_gaussian_ply
from omniscs.errors import ValidationError
from omniscs.gaussians import GaussianParams, params_from_values
from omniscs.render.sh import colors_from_sh, num_sh_bases

#: The PLY types the hand-made files use -> numpy codes (kept apart from the module's own table).
NP_CODES = {"float": "f4", "float32": "f4", "double": "f8", "float64": "f8", "uchar": "u1", "short": "i2", "int": "i4"}


def random_params(n: int, degree: int, seed: int = 0) -> GaussianParams:
    g = torch.Generator().manual_seed(seed)

    def randn(*shape: int, scale: float = 1.0) -> torch.Tensor:
        return torch.randn(*shape, generator=g) * scale

    quats = randn(n, 4, scale=3.0)  # unnormalised
    quats[:1] = 0.0                 # a zero quaternion: the identity, allowed
    return GaussianParams(means=randn(n, 3, scale=20.0), quats=quats, log_scales=randn(n, 3, scale=3.0) - 4.0,
                          opacity_logits=randn(n, scale=30.0), sh_dc=randn(n, 3),
                          sh_rest=randn(n, num_sh_bases(degree) - 1, 3, scale=0.3))


def assert_params_equal(a: GaussianParams, b: GaussianParams) -> None:
    for name, value in a.as_dict().items():
        other = getattr(b, name)
        assert other.dtype == torch.float32 and torch.equal(value, other), name


def columns_of(p: GaussianParams) -> dict[str, np.ndarray]:
    """3DGS property name -> [N] float32 values, spelled out here (channel-major f_rest)."""
    cols = {name: p.means[:, i] for i, name in enumerate("xyz")}
    cols |= {f"f_dc_{c}": p.sh_dc[:, c] for c in range(3)}
    k1 = p.sh_rest.shape[1]
    cols |= {f"f_rest_{c * k1 + k}": p.sh_rest[:, k, c] for c in range(3) for k in range(k1)}
    cols["opacity"] = p.opacity_logits
    cols |= {f"scale_{i}": p.log_scales[:, i] for i in range(3)}
    cols |= {f"rot_{i}": p.quats[:, i] for i in range(4)}
    return {k: v.numpy() for k, v in cols.items()}


def hand_ply(path, fmt: str, props: list[tuple[str, str, np.ndarray]], n: int, extra_header: tuple[str, ...] = (),
             trailer: bytes = b"") -> None:
    """A PLY file written by hand: ``props`` are (PLY type, name, [n] values) in file order."""
    lines = ["ply", f"format {fmt} 1.0", "comment written by hand", f"element vertex {n}",
             *(f"property {t} {name}" for t, name, _ in props), *extra_header, "end_header"]
    header = ("\n".join(lines) + "\n").encode("ascii")
    if fmt == "ascii":
        def text(t, v):
            return str(int(v)) if NP_CODES[t][0] in "iu" else repr(float(v))
        body = "".join(" ".join(text(t, v[i]) for t, _, v in props) + "\n" for i in range(n)).encode("ascii")
    else:
        order = "<" if fmt == "binary_little_endian" else ">"
        table = np.zeros(n, np.dtype([(name, order + NP_CODES[t]) for t, name, _ in props]))
        for _, name, values in props:
            table[name] = values
        body = table.tobytes()
    path.write_bytes(header + body + trailer)


def standard_props(p: GaussianParams, ply_type: str = "float") -> list[tuple[str, str, np.ndarray]]:
    return [(ply_type, name, values) for name, values in columns_of(p).items()]


def read_error(path) -> str:
    with pytest.raises(ValidationError) as info:
        read_gaussian_ply(path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message
    return message


# --- round trip and the written layout -------------------------------------------------------------------------------

@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_round_trip_is_bit_exact(tmp_path, degree):
    params = random_params(257, degree, seed=degree)
    path = write_gaussian_ply(params, tmp_path / "splat.ply")
    assert path == tmp_path / "splat.ply"
    back = read_gaussian_ply(path)
    assert back.sh_degree == degree
    assert_params_equal(params, back)


def test_empty_set_round_trips_with_its_degree(tmp_path):
    back = read_gaussian_ply(write_gaussian_ply(random_params(0, 2), tmp_path / "empty.ply"))
    assert len(back) == 0 and back.sh_degree == 2 and back.sh_rest.shape == (0, 8, 3)


def test_writer_takes_tensors_that_need_gradients_and_overwrites_atomically(tmp_path):
    params = GaussianParams(**{k: v.clone().requires_grad_(True) for k, v in random_params(9, 1).as_dict().items()})
    path = tmp_path / "splat.ply"
    path.write_bytes(b"an older file")
    write_gaussian_ply(params, path)
    assert [f.name for f in tmp_path.iterdir()] == ["splat.ply"]  # no temporary sibling left behind
    assert_params_equal(params.detached(), read_gaussian_ply(path))


def test_written_file_is_the_standard_3dgs_layout(tmp_path):
    n, k1 = 4, 3
    params = random_params(n, 1)
    rest = torch.tensor([[100.0 * c + k for c in range(3)] for k in range(k1)]).expand(n, k1, 3)  # [N, k, c]
    params = GaussianParams(**{**params.as_dict(), "sh_rest": rest.contiguous()})
    data = write_gaussian_ply(params, tmp_path / "splat.ply").read_bytes()

    end = data.index(b"end_header\n") + len(b"end_header\n")
    header = data[:end].decode("ascii").splitlines()
    names = ["x", "y", "z", "nx", "ny", "nz", "f_dc_0", "f_dc_1", "f_dc_2", *(f"f_rest_{i}" for i in range(9)),
             "opacity", "scale_0", "scale_1", "scale_2", "rot_0", "rot_1", "rot_2", "rot_3"]
    assert header == ["ply", "format binary_little_endian 1.0", f"element vertex {n}",
                      *(f"property float {name}" for name in names), "end_header"]
    assert ply_header_properties(tmp_path / "splat.ply") == ("binary_little_endian", names, n)

    body = np.frombuffer(data[end:], "<f4")
    assert body.size == n * len(names)  # nothing else after the vertices
    table = dict(zip(names, body.reshape(n, len(names)).T))
    for c in range(3):      # channel-major: all red coefficients first, then green, then blue
        for k in range(k1):
            assert (table[f"f_rest_{c * k1 + k}"] == 100 * c + k).all()
    assert all((table[a] == 0).all() for a in ("nx", "ny", "nz"))
    assert np.array_equal(np.stack([table[f"rot_{i}"] for i in range(4)], 1), params.quats.numpy())  # w, x, y, z
    assert np.array_equal(table["opacity"], params.opacity_logits.numpy())
    assert np.array_equal(table["scale_2"], params.log_scales[:, 2].numpy())
    assert np.array_equal(table["f_dc_1"], params.sh_dc[:, 1].numpy())


def test_colours_of_read_gaussians_equal_the_originals(tmp_path):
    params = random_params(64, 3, seed=7)
    back = read_gaussian_ply(write_gaussian_ply(params, tmp_path / "splat.ply"))
    dirs = torch.randn(3, 64, 3, generator=torch.Generator().manual_seed(1))
    for degree in range(4):
        assert torch.equal(colors_from_sh(degree, back.sh, dirs), colors_from_sh(degree, params.sh, dirs))


def test_project_made_gaussians_keep_their_colour(tmp_path):
    rgb = torch.tensor([[0.9, 0.1, 0.2], [0.0, 0.5, 1.0]])
    params = params_from_values(torch.zeros(2, 3), torch.full((2, 3), 0.1), torch.tensor([0.3, 0.99]), rgb, 0)
    back = read_gaussian_ply(write_gaussian_ply(params, tmp_path / "splat.ply"))
    assert torch.allclose(colors_from_sh(0, back.sh, torch.ones(1, 2, 3))[0], rgb, atol=1e-6)


# --- files from other tools ------------------------------------------------------------------------------------------

FACES = ("element face 2", "property list uchar int vertex_indices")


def face_trailer(fmt: str) -> bytes:
    if fmt == "ascii":
        return b"3 0 1 2\n3 1 2 3\n"
    order = "<" if fmt == "binary_little_endian" else ">"
    face = np.dtype([("n", "u1"), ("i", order + "i4", 3)])
    return np.array([(3, (0, 1, 2)), (3, (1, 2, 3))], face).tobytes()


@pytest.mark.parametrize("fmt, ply_type, shuffle, normals, faces", [
    ("binary_little_endian", "double", True, False, False),
    ("binary_little_endian", "float32", True, True, True),
    ("binary_big_endian", "float", True, False, True),
    ("ascii", "float", False, True, False),
    ("ascii", "double", True, False, True),
])
def test_other_layouts_read_to_the_same_params(tmp_path, fmt, ply_type, shuffle, normals, faces):
    params = random_params(11, 2, seed=3)
    props = standard_props(params, ply_type)
    n = len(params)
    if normals:
        props = props[:3] + [(ply_type, a, np.zeros(n)) for a in ("nx", "ny", "nz")] + props[3:]
    props.append(("uchar", "red", np.arange(n) % 256))  # extra properties of other types are ignored
    props.append(("short", "filter_3D", -np.arange(n)))
    if shuffle:
        props = [props[i] for i in np.random.default_rng(5).permutation(len(props))]
    path = tmp_path / "other.ply"
    hand_ply(path, fmt, props, n, FACES if faces else (), face_trailer(fmt) if faces else b"")
    assert_params_equal(params, read_gaussian_ply(path))
    assert ply_header_properties(path) == (fmt, [name for _, name, _ in props], n)


def test_windows_line_endings_in_the_header_are_read(tmp_path):
    params = random_params(5, 0)
    data = write_gaussian_ply(params, tmp_path / "splat.ply").read_bytes()
    end = data.index(b"end_header\n") + len(b"end_header\n")
    (tmp_path / "crlf.ply").write_bytes(data[:end].replace(b"\n", b"\r\n") + data[end:])
    assert_params_equal(params, read_gaussian_ply(tmp_path / "crlf.ply"))


# --- malformed files -------------------------------------------------------------------------------------------------

def without(props, *names):
    return [p for p in props if p[1] not in names]


def with_value(props, name, row, value):
    out = [(t, n, v.astype(np.float64)) for t, n, v in props]
    next(v for _, n, v in out if n == name)[row] = value
    return out


def misnamed_rest(props):
    return [(t, f"f_rest_{int(n[7:]) + 1}" if n.startswith("f_rest_") else n, v) for t, n, v in props]


CASES = {
    "missing properties": (lambda p: without(p, "opacity", "rot_3"), "binary_little_endian",
                           r"lacks the Gaussian properties opacity, rot_3"),
    "NaN in a row": (lambda p: with_value(p, "scale_1", 2, np.nan), "binary_little_endian",
                     r"1 of 5 Gaussians have non-finite values .*vertex 2"),
    "Inf in ascii": (lambda p: with_value(p, "x", 4, np.inf), "ascii", r"1 of 5 Gaussians have non-finite .*vertex 4"),
    "f_rest count 5": (lambda p: without(p, *(f"f_rest_{i}" for i in range(5, 9))), "binary_little_endian",
                       r"5 f_rest properties; .* 0, 9, 24 or 45"),
    "f_rest misnumbered": (misnamed_rest, "binary_little_endian", r"not numbered f_rest_0 to f_rest_8"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_malformed_vertex_properties_are_named(tmp_path, case):
    damage, fmt, pattern = CASES[case]
    path = tmp_path / "bad.ply"
    hand_ply(path, fmt, damage(standard_props(random_params(5, 1))), 5)
    assert re.search(pattern, read_error(path))


def test_doubles_beyond_float32_are_an_error_not_inf(tmp_path):
    path = tmp_path / "big.ply"
    hand_ply(path, "binary_little_endian", with_value(standard_props(random_params(5, 0), "double"), "y", 3, 1e300), 5)
    assert re.search(r"1 of 5 Gaussians have non-finite values \(NaN, Inf or beyond float32; first: vertex 3\)",
                     read_error(path))


def test_truncated_bodies_are_an_error(tmp_path):
    data = write_gaussian_ply(random_params(5, 1), tmp_path / "splat.ply").read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-3])
    assert re.search(r"truncated body: 5 vertices need 520 bytes, the file has 517", read_error(tmp_path / "cut.ply"))
    hand_ply(tmp_path / "cut.txt.ply", "ascii", standard_props(random_params(5, 1)), 5)
    text = (tmp_path / "cut.txt.ply").read_bytes()
    (tmp_path / "cut.txt.ply").write_bytes(text[:text.rindex(b"\n", 0, -1) + 1])  # the last row gone
    assert "truncated ascii body: 4 of 5 vertex rows" in read_error(tmp_path / "cut.txt.ply")


def test_ascii_rows_of_the_wrong_width_are_an_error(tmp_path):
    path = tmp_path / "ragged.ply"
    hand_ply(path, "ascii", standard_props(random_params(3, 0)), 3)
    path.write_bytes(path.read_bytes().rstrip(b"\n") + b" 7\n")  # one value too many on the last row
    assert "malformed ascii vertex rows (the number of columns changed from 14 to 15" in read_error(path)
    hand_ply(path, "ascii", standard_props(random_params(3, 0)), 3)
    path.write_bytes(path.read_bytes().rstrip(b"\n") + b"x\n")  # not a number at the end of the last row
    assert re.search(r"malformed ascii vertex rows \(could not convert string '.*x' to float64 at row 2",
                     read_error(path))
    hand_ply(path, "ascii", standard_props(random_params(3, 0)), 3, extra_header=("property float w",))
    assert "ascii vertex rows have 14 values; the header lists 15 properties" in read_error(path)


HEADER_CASES = {
    "not PLY": (b"\x89PNG\r\n\x1a\n" + bytes(64), r"not a PLY file"),
    "empty": (b"", r"not a PLY file"),
    "no end_header": (b"ply\nformat binary_little_endian 1.0\nelement vertex 0\n", r"without an end_header"),
    "unknown format": (b"ply\nformat binary_middle_endian 1.0\nelement vertex 0\nend_header\n",
                       r"unknown PLY format line 'format binary_middle_endian 1.0'"),
    "no format": (b"ply\nelement vertex 0\nend_header\n", r"no format line"),
    "no vertex": (b"ply\nformat ascii 1.0\nelement face 0\nend_header\n", r"no vertex element"),
    "vertex not first": (b"ply\nformat ascii 1.0\nelement face 0\nelement vertex 0\nproperty float x\nend_header\n",
                         r"vertex element must be the first element"),
    "list in vertex": (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty list uchar float x\nend_header\n",
                       r"vertex property 'x' is a list"),
    "unknown type": (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty half x\nend_header\n",
                     r"vertex property 'x' has unknown PLY type 'half'"),
    "duplicate": (b"ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\nproperty float x\nend_header\n",
                  r"named more than once: x"),
    "bad count": (b"ply\nformat ascii 1.0\nelement vertex -3\nend_header\n", r"unexpected PLY header line"),
}


@pytest.mark.parametrize("case", list(HEADER_CASES))
def test_malformed_headers_are_an_error(tmp_path, case):
    data, pattern = HEADER_CASES[case]
    path = tmp_path / "bad.ply"
    path.write_bytes(data)
    assert re.search(pattern, read_error(path))


def test_a_missing_file_is_a_validation_error(tmp_path):
    assert "no such file" in read_error(tmp_path / "absent.ply")


def test_non_finite_params_are_not_written(tmp_path):
    params = random_params(6, 1)
    params.sh_rest[4, 2, 1] = float("nan")
    with pytest.raises(ValidationError, match=r"cannot write .*1 of 6 Gaussians have non-finite .*index 4"):
        write_gaussian_ply(params, tmp_path / "nan.ply")
    assert not (tmp_path / "nan.ply").exists()
