"""Wavefront OBJ (+ MTL + texture image) reading and writing, vectorized.

Lines are grouped by prefix (``v``, ``vt``, ``f``) and each group is parsed in one numpy call, so a
150k-face scan loads in well under a second. Faces keep their separate UV indices (``f v/vt``), so
UV seams stay intact; polygons are fan-triangulated. Only the first textured material (``map_Kd``)
is used; a mesh that uses several different textures is rejected.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from uvatar.capture.types import TexturedMesh
from uvatar.errors import InputError
from uvatar.io_utils import atomic_path, referenced_file


def _numbers(path: Path, what: str, text: bytes, rows: int, dtype, per_row: int) -> np.ndarray:
    """Parse ``rows * per_row`` whitespace-separated numbers from ``text`` in one numpy call."""
    if rows == 0:
        return np.zeros((0, per_row), dtype)
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        values = np.fromstring(text, dtype=dtype, sep=" ")  # noqa: NPY201 - text mode is supported
    if values.size != rows * per_row:
        raise InputError(path, f"malformed {what} lines (expected {per_row} numbers on each of {rows} lines)")
    return values.reshape(rows, per_row)


def _parse_faces(path: Path, lines: list[bytes], nv: int, nt: int) -> tuple[np.ndarray, np.ndarray | None]:
    """``f`` lines → (faces (F, 3), uv_faces (F, 3) or None), zero-based, fan-triangulated."""
    if not lines:
        return np.zeros((0, 3), np.int64), None
    counts = np.fromiter((len(line.split()) - 1 for line in lines), dtype=np.int64, count=len(lines))
    if counts.min() < 3:
        raise InputError(path, "a face has fewer than 3 vertices")
    first = lines[0].split()[1]
    slashes = first.count(b"/")
    has_vt = slashes >= 1 and b"//" not in first
    flat = b" ".join(lines).replace(b"f", b" ")  # drop the line keyword (no 'f' inside numbers)
    if flat.count(b"/") != slashes * int(counts.sum()):
        raise InputError(path, "faces mix index formats (v, v/vt, v/vt/vn, v//vn)")
    per_corner = slashes + 1
    flat = flat.replace(b"//", b"/0/").replace(b"/", b" ")
    idx = _numbers(path, "f", flat, int(counts.sum()), np.int64, per_corner)
    v_idx = idx[:, 0]
    t_idx = idx[:, 1] if has_vt else None

    def zero_based(a: np.ndarray, n: int, what: str) -> np.ndarray:
        a = np.where(a < 0, a + n, a - 1)  # negative indices count back from the end
        if a.size and (a.min() < 0 or a.max() >= n):
            raise InputError(path, f"face {what} index out of range (have {n})")
        return a

    v_idx = zero_based(v_idx, nv, "vertex")
    if t_idx is not None:
        t_idx = zero_based(t_idx, nt, "texture-coordinate")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    polygon, corners = [], []
    for n in np.unique(counts):  # one vectorized fan (0, k, k+1) per polygon size
        which = np.flatnonzero(counts == n)
        s = starts[which][:, None]
        k = np.arange(1, n - 1)[None, :]
        fan = np.stack([np.broadcast_to(s, (len(which), n - 2)), s + k, s + k + 1], axis=-1)
        corners.append(fan.reshape(-1, 3))
        polygon.append(np.repeat(which, n - 2))
    order = np.argsort(np.concatenate(polygon), kind="stable")  # keep the file's face order
    corners = np.concatenate(corners)[order]
    tri = v_idx[corners]
    uv_tri = t_idx[corners] if t_idx is not None else None
    return tri, uv_tri


# map_Kd's options and how many values each takes (-o, -s, -t: one to three numbers)
MTL_MAP_OPTIONS = {"-blendu": 1, "-blendv": 1, "-bm": 1, "-boost": 1, "-cc": 1, "-clamp": 1, "-imfchan": 1,
                   "-mm": 2, "-o": 3, "-s": 3, "-t": 3, "-texres": 1, "-type": 1}


def map_file_name(arguments: str) -> str:
    """The file name of a ``map_Kd`` statement's arguments: its options (``-s 1 1 1``, ``-clamp on``...)
    dropped, the rest kept whole (a name may hold spaces, as Blender writes them)."""
    words = arguments.split()
    k = 0
    while k < len(words) and words[k] in MTL_MAP_OPTIONS:
        most = MTL_MAP_OPTIONS[words[k]]
        k += 1
        taken = 0
        while taken < most and k < len(words) - 1 and (taken == 0 or _is_number(words[k])):
            k, taken = k + 1, taken + 1
    return " ".join(words[k:]).strip('"')


def _is_number(word: str) -> bool:
    try:
        float(word)
    except ValueError:
        return False
    return True


def _parse_mtl(mtl_path: Path) -> dict[str, Path]:
    """material name → texture path (``map_Kd``) for every textured material."""
    textures: dict[str, Path] = {}
    current = None
    for raw in mtl_path.read_text(errors="replace").splitlines():
        parts = raw.strip().split(None, 1)
        if not parts:
            continue
        if parts[0] == "newmtl" and len(parts) > 1:
            current = parts[1].strip()
        elif parts[0] == "map_Kd" and len(parts) > 1 and current is not None:
            name = map_file_name(parts[1])
            if name:
                textures[current] = referenced_file(mtl_path.parent, name)
    return textures


def _statement_args(data: bytes, keyword: bytes) -> list[str]:
    """Arguments of every line that starts with ``keyword`` (found with bytes.find, C speed)."""
    out, start = [], 0
    while (at := data.find(keyword, start)) >= 0:
        end = data.find(b"\n", at)
        end = len(data) if end < 0 else end
        line_start = data.rfind(b"\n", 0, at) + 1
        if not data[line_start:at].strip() and data[at + len(keyword): at + len(keyword) + 1] in (b" ", b"\t"):
            out.append(data[at + len(keyword): end].decode(errors="replace").strip())
        start = end
    return out


def obj_textures(path: Path, data: bytes | None = None) -> tuple[list[Path], dict[str, int]]:
    """The texture images named by the OBJ's materials (``mtllib`` → ``map_Kd``), each once, in the order
    the faces first use them, and the image of each textured material."""
    if data is None:
        data = path.read_bytes()
    libs, used = _statement_args(data, b"mtllib"), _statement_args(data, b"usemtl")
    textures: dict[str, Path] = {}
    for lib in libs:
        mtl = path.parent / lib
        if not mtl.is_file():
            raise InputError(mtl, "material library named by the OBJ is missing")
        textures.update(_parse_mtl(mtl))
    names = [u for u in dict.fromkeys(used) if u in textures] or list(textures)
    distinct = list(dict.fromkeys(textures[n] for n in names))
    return distinct, {n: distinct.index(t) for n, t in textures.items() if t in distinct}


def obj_texture_path(path: Path, data: bytes | None = None) -> Path | None:
    """The OBJ's texture image (the first where its materials name several, which :func:`read_obj` packs
    into one atlas), or None."""
    distinct, _ = obj_textures(path, data)
    return distinct[0] if distinct else None


def _face_materials(lines: list[bytes]) -> list[str | None]:
    """The material (``usemtl``) in force at each ``f`` line."""
    current, out = None, []
    for line in lines:               # one pass over the lines, as read_obj's own
        if line[:2] in (b"f ", b"f\t"):
            out.append(current)
        elif line[:7] in (b"usemtl ", b"usemtl\t"):
            current = line[7:].decode(errors="replace").strip()
    return out


def obj_header(path: Path) -> dict:
    """Counts and texture of an OBJ without parsing numbers (fast on big scans)."""
    data = path.read_bytes()

    def count(keyword: bytes) -> int:  # lines starting with keyword + space/tab, at C speed
        return sum(data.count(b"\n" + keyword + sep) + data.startswith(keyword + sep) for sep in (b" ", b"\t"))

    nv, nf, nvt = count(b"v"), count(b"f"), count(b"vt")
    if nv == 0 or nf == 0:
        raise InputError(path, "not a mesh: no vertices or faces")
    return {"num_vertices": nv, "num_faces": nf, "has_uvs": nvt > 0, "texture": obj_texture_path(path, data)}


def read_obj(path: Path, load_texture) -> TexturedMesh:
    data = path.read_bytes()
    lines = data.splitlines()
    v_rows = [line[1:] for line in lines if line[:2] == b"v " or line[:2] == b"v\t"]
    vt_rows = [line[2:] for line in lines if line[:3] == b"vt " or line[:3] == b"vt\t"]
    f_rows = [line for line in lines if line[:2] == b"f " or line[:2] == b"f\t"]
    if not v_rows or not f_rows:
        raise InputError(path, "not a mesh: no vertices or faces")
    ncols = len(v_rows[0].split())
    if ncols not in (3, 4, 6, 7):
        raise InputError(path, f"vertex lines have {ncols} values, expected 3 (x y z) or 6 (x y z r g b)")
    table = _numbers(path, "v", b" ".join(v_rows), len(v_rows), np.float64, ncols)
    vertices = table[:, :3]
    colors = None
    if ncols in (6, 7):                    # x y z r g b (MeshLab's and most scanners' vertex colours)
        rgb = table[:, 3:6]
        colors = np.clip(rgb / 255.0 if rgb.size and rgb.max() > 1.0 else rgb, 0.0, 1.0)
    uvs = np.zeros((0, 2))
    if vt_rows:
        tcols = len(vt_rows[0].split())
        uvs = _numbers(path, "vt", b" ".join(vt_rows), len(vt_rows), np.float64, tcols)[:, :2]
    faces, uv_faces = _parse_faces(path, f_rows, len(vertices), len(uvs))
    if uv_faces is None:
        uvs, uv_faces = np.zeros((0, 2)), np.zeros((0, 3), np.int64)
    paths, image_of = obj_textures(path, data)
    texture = load_texture(paths[0]) if paths else None
    if len(paths) > 1 and len(uv_faces):          # several images: one atlas of them (capture/texture_tiles.py)
        from uvatar.capture.texture_tiles import pack_textures

        counts = np.fromiter((len(line.split()) - 1 for line in f_rows), dtype=np.int64, count=len(f_rows))
        polygon_image = np.array([image_of.get(m, -1) for m in _face_materials(lines)], np.int64)
        face_image = np.repeat(polygon_image, counts - 2)
        texture, uvs, uv_faces = pack_textures([texture] + [load_texture(p) for p in paths[1:]], uvs, uv_faces,
                                               face_image, path)
    return TexturedMesh(vertices, faces, uvs, uv_faces, texture, colors)


def _fmt_rows(prefix: str, rows: np.ndarray, fmt: str) -> str:
    if rows.size == 0:
        return ""
    line = prefix + " " + " ".join([fmt] * rows.shape[1]) + "\n"
    return (line * rows.shape[0]) % tuple(rows.ravel())


def write_obj(path: Path, mesh: TexturedMesh, write_texture) -> None:
    """Write ``path`` (+ ``<stem>.mtl`` and ``<stem>.png`` beside it when textured), each atomically."""
    lines = [f"# uvatar: {mesh.num_vertices} vertices, {mesh.num_faces} faces\n"]
    textured = mesh.texture is not None
    if textured:
        write_texture(path.with_suffix(".png"), mesh.texture)
        mtl = f"newmtl material0\nKa 1 1 1\nKd 1 1 1\nKs 0 0 0\nillum 1\nmap_Kd {path.stem}.png\n"
        with atomic_path(path.with_suffix(".mtl")) as tmp:
            tmp.write_text(mtl)
        lines.append(f"mtllib {path.stem}.mtl\nusemtl material0\n")
    lines.append(_fmt_rows("v", mesh.vertices.astype(np.float64), "%.7g"))
    has_uv = mesh.has_uvs
    if has_uv:
        lines.append(_fmt_rows("vt", mesh.uvs.astype(np.float64), "%.7g"))
        corners = np.stack([mesh.faces + 1, mesh.uv_faces + 1], axis=-1).reshape(-1)
        lines.append("f %d/%d %d/%d %d/%d\n" * mesh.num_faces % tuple(corners))
    else:
        lines.append(_fmt_rows("f", mesh.faces + 1, "%d"))
    with atomic_path(path) as tmp:
        tmp.write_text("".join(lines))


def read_obj_reference(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Plain per-line twin of :func:`read_obj` (geometry only, for parity tests):
    → (vertices (V, 3), faces (F, 3), uvs (U, 2), uv_faces (F, 3) or (0, 3))."""
    vertices, uvs, faces, uv_faces = [], [], [], []
    for raw in Path(path).read_text().splitlines():
        parts = raw.split()
        if not parts:
            continue
        if parts[0] == "v":
            vertices.append([float(x) for x in parts[1:4]])
        elif parts[0] == "vt":
            uvs.append([float(x) for x in parts[1:3]])
        elif parts[0] == "f":
            corners = [c.split("/") for c in parts[1:]]

            def index(text: str, n: int) -> int:
                i = int(text)
                return i + n if i < 0 else i - 1

            v = [index(c[0], len(vertices)) for c in corners]
            t = [index(c[1], len(uvs)) for c in corners if len(c) > 1 and c[1]]
            for k in range(1, len(v) - 1):
                faces.append([v[0], v[k], v[k + 1]])
                if len(t) == len(v):
                    uv_faces.append([t[0], t[k], t[k + 1]])
    return (np.array(vertices).reshape(-1, 3), np.array(faces, np.int64).reshape(-1, 3),
            np.array(uvs).reshape(-1, 2), np.array(uv_faces, np.int64).reshape(-1, 3))
