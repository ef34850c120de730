"""PLY with UVs: per-vertex ``s``/``t`` (or ``u``/``v``, ``texture_u``/``texture_v``) or per-face
``texcoord`` lists; the texture is named in a ``comment TextureFile <name>`` header line.

ASCII and binary (little/big endian) bodies are read with one numpy call per element; list
properties must have the same length on every face (triangles, or uniform quads which are
fan-triangulated). Written files are binary little endian.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError
from uvatar.io_utils import atomic_path, referenced_file

_TYPES = {"char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1", "short": "i2", "int16": "i2",
          "ushort": "u2", "uint16": "u2", "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
          "float": "f4", "float32": "f4", "double": "f8", "float64": "f8"}
_U_NAMES = ("s", "u", "texture_u", "texture_s")
_V_NAMES = ("t", "v", "texture_v", "texture_t")


def _read_header(path: Path, fh) -> dict:
    if fh.readline().strip() != b"ply":
        raise InputError(path, "not a PLY file (missing 'ply' magic)")
    header = {"format": None, "elements": [], "texture": None}
    while True:
        raw = fh.readline()
        if not raw:
            raise InputError(path, "PLY header has no 'end_header'")
        parts = raw.decode("latin-1").split()
        if not parts:
            continue
        if parts[0] == "end_header":
            break
        if parts[0] == "format":
            header["format"] = parts[1]
        elif parts[0] == "comment" and len(parts) > 2 and parts[1].lower() == "texturefile":
            header["texture"] = raw.decode("latin-1").split(None, 2)[2].strip()
        elif parts[0] == "element":
            header["elements"].append({"name": parts[1], "count": int(parts[2]), "props": []})
        elif parts[0] == "property":
            if not header["elements"]:
                raise InputError(path, "PLY property before any element")
            try:
                if parts[1] == "list":
                    prop = (parts[4], _TYPES[parts[2]], _TYPES[parts[3]])
                else:
                    prop = (parts[2], None, _TYPES[parts[1]])
            except (KeyError, IndexError):
                raise InputError(path, f"bad PLY property line: {raw.decode('latin-1').strip()}") from None
            header["elements"][-1]["props"].append(prop)
    if header["format"] not in ("ascii", "binary_little_endian", "binary_big_endian"):
        raise InputError(path, f"unknown PLY format {header['format']!r}")
    header["data_offset"] = fh.tell()
    return header



def _read_element_binary(path: Path, buf: memoryview, offset: int, element: dict, endian: str):
    """→ (columns dict name → (N,) or (N, k) array, new offset). Lists must have a fixed length."""
    n = element["count"]
    props = element["props"]
    # peek the list lengths of the first row to build a fixed-size record type
    fields, pos = [], offset
    for name, count_type, item_type in props:
        if count_type is None:
            fields.append((name, endian + item_type))
            pos += np.dtype(item_type).itemsize
        else:
            k = int(np.frombuffer(buf, dtype=endian + count_type, count=1, offset=pos)[0]) if n else 0
            fields.append((name + "__count", endian + count_type))
            fields.append((name, endian + item_type, (k,)))
            pos += np.dtype(count_type).itemsize + k * np.dtype(item_type).itemsize
    dtype = np.dtype(fields)
    if offset + n * dtype.itemsize > len(buf):
        raise InputError(path, f"PLY body too short for {n} {element['name']} records "
                               "(truncated file, or list lengths vary: only fixed-size polygons are supported)")
    rec = np.frombuffer(buf, dtype=dtype, count=n, offset=offset)
    columns = {}
    for name, count_type, _ in props:
        if count_type is not None:
            counts = rec[name + "__count"]
            if n and np.any(counts != counts[0]):
                raise InputError(path, f"PLY '{name}' lists vary in length; triangulate the mesh first")
        columns[name] = np.asarray(rec[name])
    return columns, offset + n * dtype.itemsize


def _read_ascii(path: Path, body: bytes, elements: list[dict]) -> dict[str, dict]:
    lines = body.splitlines()
    out, row = {}, 0
    for element in elements:
        n = element["count"]
        chunk = [line for line in lines[row: row + n]]
        if len(chunk) < n:
            raise InputError(path, f"PLY body too short for {n} {element['name']} rows")
        row += n
        if n == 0:
            out[element["name"]] = {p[0]: np.zeros(0) for p in element["props"]}
            continue
        ncols = len(chunk[0].split())
        import warnings

        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            values = np.fromstring(b" ".join(chunk), dtype=np.float64, sep=" ")  # noqa: NPY201
        if values.size != ncols * n:
            raise InputError(path, f"PLY {element['name']} rows vary in length or are not numeric")
        table = values.reshape(n, ncols)
        columns, col = {}, 0
        for name, count_type, _ in element["props"]:
            if count_type is None:
                columns[name] = table[:, col]
                col += 1
            else:
                k = int(table[0, col])
                columns[name] = table[:, col + 1: col + 1 + k]
                col += 1 + k
        out[element["name"]] = columns
    return out


def ply_header(path: Path) -> dict:
    with open(path, "rb") as fh:
        header = _read_header(path, fh)
    counts = {e["name"]: e["count"] for e in header["elements"]}
    names = {e["name"]: [p[0] for p in e["props"]] for e in header["elements"]}
    has_uvs = (any(u in names.get("vertex", []) for u in _U_NAMES)
               or any(p in names.get("face", []) for p in ("texcoord", "texcoords")))
    if not counts.get("vertex") or not counts.get("face"):
        raise InputError(path, "not a mesh: no vertices or faces")
    texture = referenced_file(path.parent, header["texture"]) if header["texture"] else None
    return {"num_vertices": counts["vertex"], "num_faces": counts["face"], "has_uvs": has_uvs,
            "texture": texture}


def _fan(rows: np.ndarray) -> np.ndarray:
    """(F, n) polygons → (F*(n-2), 3) triangles, fan from corner 0."""
    n = rows.shape[1]
    k = np.arange(1, n - 1)
    return np.stack([np.repeat(rows[:, :1], n - 2, axis=1), rows[:, k], rows[:, k + 1]], -1).reshape(-1, 3)


def read_ply(path: Path, load_texture) -> TexturedMesh:
    data = path.read_bytes()
    import io

    header = _read_header(path, io.BytesIO(data))
    fmt, offset = header["format"], header["data_offset"]
    if fmt == "ascii":
        elements = _read_ascii(path, data[offset:], header["elements"])
    else:
        endian = "<" if fmt == "binary_little_endian" else ">"
        elements, buf = {}, memoryview(data)
        for element in header["elements"]:
            elements[element["name"]], offset = _read_element_binary(path, buf, offset, element, endian)
    vert, face = elements.get("vertex"), elements.get("face")
    if not vert or not all(c in vert for c in "xyz"):
        raise InputError(path, "PLY has no vertex x/y/z")
    vertices = np.stack([vert["x"], vert["y"], vert["z"]], -1)
    if face is None or not any(len(v) for v in face.values()):     # a point cloud: read_mesh says if it may be
        return TexturedMesh(vertices, np.zeros((0, 3), np.int64), np.zeros((0, 2)), np.zeros((0, 3), np.int64),
                            None, _vertex_colors(vert, header["elements"]))
    index_name = next((n for n in ("vertex_indices", "vertex_index") if n in face), None)
    if index_name is None:
        raise InputError(path, "PLY faces have no vertex_indices list")
    if len(face[index_name]) == 0 or len(vertices) == 0:
        raise InputError(path, f"PLY has {len(face[index_name])} faces and {len(vertices)} vertices; a mesh needs both")
    try:
        polys = np.asarray(face[index_name]).astype(np.int64).reshape(len(face[index_name]), -1)
    except (ValueError, TypeError):  # lists of different lengths (mixed polygons are fanned per size only)
        raise InputError(path, "PLY faces mix polygon sizes; triangulate the mesh") from None
    if polys.shape[1] < 3:
        raise InputError(path, "PLY faces have fewer than 3 vertices")
    if polys.size and (polys.min() < 0 or polys.max() >= len(vertices)):
        raise InputError(path, "PLY face vertex index out of range")
    faces = _fan(polys)
    u_name = next((n for n in _U_NAMES if n in vert), None)
    v_name = next((n for n in _V_NAMES if n in vert), None)
    tc_name = next((n for n in ("texcoord", "texcoords") if n in face), None)
    if tc_name is not None:
        tc = np.asarray(face[tc_name], np.float64).reshape(len(polys), -1)
        if tc.shape[1] != 2 * polys.shape[1]:
            raise InputError(path, f"PLY {tc_name} has {tc.shape[1]} values per face, expected "
                                   f"{2 * polys.shape[1]}")
        corner_uv = np.ascontiguousarray(tc.reshape(-1, 2))
        # one complex per (u, v): sorts as np.unique(axis=0) does (u, then v), ~6x faster on a scan
        unique, inverse = np.unique(corner_uv.view(np.complex128).ravel(), return_inverse=True)
        uvs = np.stack([unique.real, unique.imag], -1)
        uv_faces = _fan(inverse.reshape(len(polys), -1))
    elif u_name and v_name:
        uvs = np.stack([vert[u_name], vert[v_name]], -1)
        uv_faces = faces
    else:
        uvs, uv_faces = np.zeros((0, 2)), np.zeros((0, 3), np.int64)
    texture = None
    if header["texture"]:
        texture = load_texture(referenced_file(path.parent, header["texture"]))
    return TexturedMesh(vertices, faces, uvs, uv_faces, texture, _vertex_colors(vert, header["elements"]))


def _vertex_colors(vert: dict, elements: list[dict]) -> np.ndarray | None:
    """(V, 3) colours in [0, 1] from ``red``/``green``/``blue`` (or ``diffuse_red``...) vertex
    properties: integers scaled by their type's maximum, floats as they are; None without them."""
    for prefix in ("", "diffuse_"):
        names = [prefix + c for c in ("red", "green", "blue")]
        if all(n in vert for n in names):
            types = {p[0]: p[2] for e in elements if e["name"] == "vertex" for p in e["props"]}
            kind = np.dtype(types.get(names[0]) or "f4")
            rgb = np.stack([np.asarray(vert[n], np.float64) for n in names], -1)
            if kind.kind in "ui":
                rgb = rgb / np.iinfo(kind).max
            elif rgb.size and rgb.max() > 1.0:           # an ASCII file's 0-255 integers read as numbers
                rgb = rgb / 255.0
            return np.clip(rgb, 0.0, 1.0).astype(np.float32)
    return None


def write_ply(path: Path, mesh: TexturedMesh, write_texture) -> None:
    """Binary little-endian PLY; UVs per vertex when they share the vertex indexing, else per face."""
    per_vertex = mesh.has_uvs and len(mesh.uvs) == mesh.num_vertices and np.array_equal(mesh.uv_faces, mesh.faces)
    per_face = mesh.has_uvs and not per_vertex
    head = ["ply", "format binary_little_endian 1.0", "comment written by uvatar"]
    if mesh.texture is not None:
        write_texture(path.with_suffix(".png"), mesh.texture)
        head.append(f"comment TextureFile {path.stem}.png")
    head += [f"element vertex {mesh.num_vertices}", "property float x", "property float y", "property float z"]
    vfields = [("x", "<f4"), ("y", "<f4"), ("z", "<f4")]
    if per_vertex:
        head += ["property float s", "property float t"]
        vfields += [("s", "<f4"), ("t", "<f4")]
    head += [f"element face {mesh.num_faces}", "property list uchar int vertex_indices"]
    ffields = [("n", "u1"), ("vi", "<i4", (3,))]
    if per_face:
        head.append("property list uchar float texcoord")
        ffields += [("m", "u1"), ("tc", "<f4", (6,))]
    head.append("end_header")
    vrec = np.empty(mesh.num_vertices, dtype=vfields)
    vrec["x"], vrec["y"], vrec["z"] = mesh.vertices.T
    if per_vertex:
        vrec["s"], vrec["t"] = mesh.uvs.T
    frec = np.empty(mesh.num_faces, dtype=ffields)
    frec["n"], frec["vi"] = 3, mesh.faces
    if per_face:
        frec["m"], frec["tc"] = 6, mesh.uvs[mesh.uv_faces].reshape(-1, 6)
    with atomic_path(path) as tmp, open(tmp, "wb") as fh:
        fh.write(("\n".join(head) + "\n").encode("ascii"))
        fh.write(vrec.tobytes())
        fh.write(frec.tobytes())
