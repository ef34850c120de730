"""Corto meshes decoded: the one owner of the ``.crt`` bitstream (Federico Ponchio's Corto, ISTI-CNR,
the mesh codec of UVOL 1 volumetric videos, whose ``.drcs`` files are Corto frames end to end).

A ``.crt`` holds a header (magic ``0x787A6300``, exif strings, each attribute's codec, quantization
step, components, type and strategy; vertex and face counts), then the face groups, the connectivity,
and one stream per attribute. Written from Corto's C++ decoder and its JavaScript port (the one the
UVOL 1 player runs); checked against the C++ decoder's own output (``corto -P``,
``tests/fixtures/corto/``).

- **Entropy**: Tunstall codes (a 256-word dictionary built from the symbols' probabilities; the
  dictionary in Python, the expansion of a stream in numpy) over the bit lengths of the values, whose
  bits follow MSB first in 32-bit words (read in numpy from the lengths' running sums).
- **Connectivity**: an edge-front walk driven by the CLERS codes (vertex, left, right, end, boundary,
  delay, split). Each face depends on the front the ones before it left, so it is sequential by nature:
  :func:`decode_faces` is the reference, a loop over faces in Python, run compiled in one Warp thread
  where the ``kernels`` extra is installed (:mod:`uvatar.capture.corto_warp`). The walk also gives each
  new vertex its prediction (the parallelogram's three vertices).
- **Attributes**: positions by parallelogram prediction, UVs and other generic attributes by the
  prediction's first vertex (a chain through earlier vertices: the same loop and kernel), then times
  their quantization step in float32 as the C++ decoder does; normals in octahedral coordinates, as
  differences (``DIFF``) or as corrections of the normals the faces estimate (``ESTIMATED``, ``BORDER``);
  colours in Corto's YCoCg-like transform. Point clouds (no faces) by running sums.

A malformed stream raises :class:`CortoError` (a ValueError) saying what is wrong; the importer names
the file and the frame.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass, field

import numpy as np

from uvatar.capture.corto_entropy import BitReader, CortoError, Stream, decode_array, decode_values, tunstall
from uvatar.capture.corto_warp import decode_faces_warp, predict_values_warp
from uvatar.geometry.warp_torch import warp_available

__all__ = ["CortoError", "CortoMesh", "decode_corto", "decode_faces", "predict_values", "corto_header"]

MAGIC = 0x787A6300
GENERIC, NORMAL, COLOR = 1, 2, 3                  # attribute codecs
PARALLEL, CORRELATED = 1, 2                       # strategy bits
DIFF, ESTIMATED, BORDER = 0, 1, 2                 # normal predictions
TYPES = ("uint32", "int32", "uint16", "int16", "uint8", "int8", "float", "double")
VERTEX, LEFT, RIGHT, END, BOUNDARY, DELAY, SPLIT = range(7)   # CLERS codes


@dataclass
class CortoMesh:
    """A decoded ``.crt``: (n, 3) float32 ``positions`` (the file's units), (m, 3) int64 ``faces`` (empty
    for a point cloud), per-vertex ``uvs`` (n, 2) float32 as stored (OBJ's convention: v up),
    ``normals`` (n, 3) float32 and ``colors`` (n, 3 or 4) uint8 where the file has them, every other
    attribute by name in ``extra``; ``groups``: (end face, properties) per face group; ``exif``."""

    positions: np.ndarray
    faces: np.ndarray
    uvs: np.ndarray | None = None
    normals: np.ndarray | None = None
    colors: np.ndarray | None = None
    extra: dict[str, np.ndarray] = field(default_factory=dict)
    groups: list[tuple[int, dict[str, str]]] = field(default_factory=list)
    exif: dict[str, str] = field(default_factory=dict)


@dataclass
class _Attribute:
    name: str
    codec: int
    q: float
    components: int
    type: int
    strategy: int


# -- connectivity ----------------------------------------------------------------------------------


def decode_faces(clers: np.ndarray, split_words: np.ndarray, group_ends: list[int], nvert: int, nface: int,
                 max_front: int) -> tuple[np.ndarray, np.ndarray, int]:
    """The reference edge-front walk: CLERS codes (uint8), the split indices' bit stream (uint32 words),
    each group's end face → ((nface, 3) int64 faces, (nvert, 3) int64 predictions: each vertex's
    parallelogram (a, b, c), predicted as a + b - c; how many vertices the walk made). A Python loop
    over faces; its compiled twin is :func:`uvatar.capture.corto_warp.decode_faces_warp`."""
    faces = [0] * (3 * nface)
    prediction = [0] * (3 * nvert)
    front = [0] * (5 * max_front)
    bits = BitReader(split_words)
    split_bits = max(nvert, 1).bit_length()   # ilog2(nvert) + 1
    ncler, cler, vertex_count, start = len(clers), 0, 0, 0
    clers = clers.tolist()
    try:
        for group_end in group_ends:
            end = 3 * group_end
            front_count, order, order_front, delayed, new_edge = 0, [], 0, [], -1
            while start < end:
                if new_edge == -1 and order_front >= len(order) and not delayed:   # a new component
                    last = vertex_count - 1
                    if cler >= ncler:
                        raise CortoError("the connectivity ends early: truncated or corrupt")
                    split = bits.read(3) if clers[cler] == SPLIT else 0
                    cler += 1
                    vindex = []
                    for k in range(3):
                        if split & (1 << k):
                            v = bits.read(split_bits)
                            if v >= nvert:
                                raise CortoError("a split names a vertex past the vertex count: corrupt")
                        else:
                            prediction[3 * vertex_count:3 * vertex_count + 3] = (last, last, last)
                            last = v = vertex_count
                            vertex_count += 1
                        vindex.append(v)
                        faces[start] = v
                        start += 1
                    e = front_count
                    for a, b, c, p, nx in ((1, 2, 0, 2, 1), (2, 0, 1, 0, 2), (0, 1, 2, 1, 0)):
                        order.append(front_count)
                        front[front_count:front_count + 5] = (vindex[a], vindex[b], vindex[c], e + 5 * p, e + 5 * nx)
                        front_count += 5
                    continue
                if new_edge != -1:
                    edge, new_edge = new_edge, -1
                elif order_front < len(order):
                    edge = order[order_front]
                    order_front += 1
                else:
                    edge = delayed.pop()
                if front[edge] < 0:                                                # deleted
                    continue
                if cler >= ncler:
                    raise CortoError("the connectivity ends early: truncated or corrupt")
                c = clers[cler]
                cler += 1
                if c == BOUNDARY:
                    continue
                v0, v1, v2, prev, nxt = front[edge:edge + 5]
                new_edge = front_count
                if c == VERTEX or c == SPLIT:
                    if c == SPLIT:
                        opposite = bits.read(split_bits)
                    else:
                        prediction[3 * vertex_count:3 * vertex_count + 3] = (v1, v0, v2)
                        opposite = vertex_count
                        vertex_count += 1
                    front[prev + 4] = new_edge
                    front[nxt + 3] = new_edge + 5
                    front[front_count:front_count + 5] = (v0, opposite, v1, prev, new_edge + 5)
                    front_count += 5
                    order.append(front_count)
                    front[front_count:front_count + 5] = (opposite, v1, v0, new_edge, nxt)
                    front_count += 5
                elif c == LEFT:
                    front[front[prev + 3] + 4] = new_edge
                    front[nxt + 3] = new_edge
                    opposite = front[prev]
                    front[front_count:front_count + 5] = (opposite, v1, v0, front[prev + 3], nxt)
                    front_count += 5
                    front[prev] = -1
                elif c == RIGHT:
                    front[front[nxt + 4] + 3] = new_edge
                    front[prev + 4] = new_edge
                    opposite = front[nxt + 1]
                    front[front_count:front_count + 5] = (v0, opposite, v1, prev, front[nxt + 4])
                    front_count += 5
                    front[nxt] = -1
                elif c == DELAY:
                    delayed.append(edge)
                    new_edge = -1
                    continue
                elif c == END:
                    front[front[prev + 3] + 4] = front[nxt + 4]
                    front[front[nxt + 4] + 3] = front[prev + 3]
                    opposite = front[prev]
                    front[prev] = front[nxt] = -1
                    new_edge = -1
                else:
                    raise CortoError(f"connectivity code {c} is none of Corto's: corrupt")
                if max(v0, v1, opposite) >= nvert or min(v0, v1, opposite) < 0:
                    raise CortoError("a face names a vertex past the vertex count: corrupt")
                faces[start:start + 3] = (v1, v0, opposite)
                start += 3
    except IndexError:
        raise CortoError("the connectivity walks off its edge front: corrupt") from None
    return (np.asarray(faces, np.int64).reshape(-1, 3), np.asarray(prediction, np.int64).reshape(-1, 3),
            vertex_count)


def predict_values(values: np.ndarray, prediction: np.ndarray, parallelogram: bool) -> np.ndarray:
    """Undo the prediction of (n, c) integer residuals in vertex order: each vertex adds its
    parallelogram (a + b - c) or its first predictor (a), both earlier vertices, in 32-bit wraparound as
    the C++ decoder's ints. The reference: a Python loop over vertices."""
    out = values.astype(np.int64).tolist()
    pred = prediction.tolist()
    for i in range(1, len(out)):
        a, b, c = pred[i]
        row, ra = out[i], out[a]
        if parallelogram:
            rb, rc = out[b], out[c]
            out[i] = [row[k] + ra[k] + rb[k] - rc[k] for k in range(len(row))]
        else:
            out[i] = [row[k] + ra[k] for k in range(len(row))]
    return _wrap32(np.asarray(out, np.int64).reshape(values.shape))


def _check_prediction(prediction: np.ndarray) -> None:
    """Every vertex after the first predicted from vertices before it (what both twins assume)."""
    later = prediction[1:]
    if len(later) and ((later < 0) | (later >= np.arange(1, len(prediction))[:, None])).any():
        raise CortoError("a vertex predicted from one not yet decoded: corrupt")


def _wrap32(v: np.ndarray) -> np.ndarray:
    return ((v + (1 << 31)) % (1 << 32)) - (1 << 31)


# -- attributes -------------------------------------------------------------------------------------


def _octa_from_normals(e: np.ndarray, unit: int) -> np.ndarray:
    """Corto's toOcta of float normals (float32 arithmetic, truncated toward zero) → (n, 2) int64."""
    e = e.astype(np.float32)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = e[:, :2] / np.abs(e).sum(1, dtype=np.float32)[:, None]
    folded = np.stack([np.float32(1) - np.abs(p[:, 1]), np.float32(1) - np.abs(p[:, 0])], 1)
    folded = np.where(e[:, :2] < 0, -folded, folded)
    p = np.where((e[:, 2] < 0)[:, None], folded, p)
    return np.trunc(np.nan_to_num(p * np.float32(unit))).astype(np.int64)


def _sphere_from_octa(v: np.ndarray, unit: int) -> np.ndarray:
    """Corto's toSphere: (n, 2) octahedral integers → (n, 3) float32 unit normals."""
    a = np.abs(v)
    n = np.stack([v[:, 0], v[:, 1], unit - a[:, 0] - a[:, 1]], 1).astype(np.float32)
    sign = np.where(v > 0, 1, -1)
    folded = np.stack([sign[:, 0] * (unit - a[:, 1]), sign[:, 1] * (unit - a[:, 0])], 1).astype(np.float32)
    n[:, :2] = np.where((n[:, 2] < 0)[:, None], folded, n[:, :2])
    norm = np.sqrt((n * n).sum(1, dtype=np.float32))
    return (n / norm[:, None]).astype(np.float32)


def _estimated_normals(coords: np.ndarray, faces: np.ndarray, nvert: int) -> np.ndarray:
    """Each vertex's sum of its faces' cross products from the integer positions, in float32 and face
    order (the C++ decoder's)."""
    p = coords.astype(np.float32)
    n = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]]).astype(np.float32)
    out = np.zeros((nvert, 3), np.float32)
    for k in range(3):
        np.add.at(out, faces[:, k], n)
    return out


def _boundary(faces: np.ndarray, nvert: int) -> np.ndarray:
    """Corto's boundary mark: the XOR of each vertex's neighbours over its faces (0 inside a closed fan)."""
    mark = np.zeros(nvert, np.int64)
    for k in range(3):
        np.bitwise_xor.at(mark, faces[:, k], faces[:, (k + 1) % 3] ^ faces[:, (k + 2) % 3])
    return mark != 0


def _colors(values: np.ndarray, qc: bytes, components: int) -> np.ndarray:
    """Corto's colour transform back to RGB(A), 8-bit as the decoder stores it."""
    v = values.astype(np.int64)
    rgb = np.stack([(v[:, 2] + v[:, 0]) * qc[0], v[:, 0] * qc[1], (v[:, 1] + v[:, 0]) * qc[2]], 1)  # uint8 wraps
    if components == 4:
        rgb = np.concatenate([rgb, v[:, 3:4] * qc[3]], 1)
    return (rgb & 0xFF).astype(np.uint8)


def _header(stream: Stream) -> tuple[dict[str, str], list[_Attribute], int, int]:
    if len(stream.data) < 8 or struct.unpack_from("<I", stream.data)[0] != MAGIC:
        raise CortoError("not a Corto mesh (missing the 0x787A6300 magic)")
    stream.take(8)                                  # magic, version
    if stream.u8() not in (0, 1, 2):                # entropy: Corto's decoders read Tunstall for every value
        raise CortoError("an entropy coder Corto's decoders do not have: corrupt")
    exif = {stream.string(): stream.string() for _ in range(stream.count("the exif count", 10_000))}
    attributes = []
    for _ in range(stream.count("the attribute count", 64)):
        name, codec, q = stream.string(), stream.i32(), stream.f32()
        components, kind, strategy = stream.u8(), stream.u8(), stream.u8()
        if not 1 <= components <= 4 or kind >= len(TYPES):
            raise CortoError(f"attribute {name!r} has {components} components of type {kind}: corrupt")
        attributes.append(_Attribute(name, codec, q, components, kind, strategy))
    nvert, nface = stream.count("the vertex count"), stream.count("the face count")
    return exif, attributes, nvert, nface


def corto_header(data: bytes) -> dict:
    """A ``.crt``'s counts, attribute names and quantization steps (the file's units per integer step),
    nothing decoded."""
    exif, attributes, nvert, nface = _header(Stream(data))
    return {"vertices": nvert, "faces": nface, "attributes": [a.name for a in attributes],
            "steps": {a.name: a.q for a in attributes}, "exif": exif}


def _groups(stream: Stream, nface: int) -> list[tuple[int, dict[str, str]]]:
    groups = []
    for _ in range(stream.count("the group count", 1 << 20)):
        end = stream.count("a group's end face")
        props = {stream.string(): stream.string() for _ in range(stream.u8())}
        groups.append((end, props))
    ends = [g[0] for g in groups]
    if nface and (not ends or ends != sorted(ends) or ends[-1] != nface):
        raise CortoError(f"face groups ending at {ends[:4]}... for {nface} faces: corrupt")
    return groups


def decode_corto(data: bytes, fast: bool = True) -> CortoMesh:
    """A ``.crt`` frame's bytes → :class:`CortoMesh`. ``fast``: the connectivity and the predictions
    through their Warp twins where the kernels extra is installed (else and with False, the reference)."""
    stream = Stream(bytes(data))
    exif, attributes, nvert, nface = _header(stream)
    groups = _groups(stream, nface)
    faces = np.zeros((0, 3), np.int64)
    prediction = None
    fast = fast and warp_available("Corto connectivity and predictions")
    walk = decode_faces_warp if fast else None
    if nface:
        max_front = stream.count("the edge front's size")
        clers = tunstall(stream)
        split_words = stream.bitstream()
        args = (clers, split_words, [g[0] for g in groups], nvert, nface, max_front)
        decoded = walk(*args) if walk is not None else None
        faces, prediction, made = decoded if decoded is not None else decode_faces(*args)
        if made != nvert:
            raise CortoError(f"the connectivity makes {made} vertices, the header says {nvert}: corrupt")
    residuals: dict[str, tuple[np.ndarray, int]] = {}
    extra_bytes: dict[str, bytes] = {}
    for a in attributes:
        if a.codec == NORMAL:
            extra_bytes[a.name] = bytes([stream.u8()])
            residuals[a.name] = decode_array(stream, nvert, 2)
        else:
            if a.codec == COLOR:                       # a step per channel, then 8-bit values
                extra_bytes[a.name] = stream.take(a.components)
            if a.strategy & CORRELATED and a.codec != COLOR:
                residuals[a.name] = decode_array(stream, nvert, a.components)
            else:
                residuals[a.name] = (decode_values(stream, nvert, a.components), nvert)
    if prediction is not None:
        _check_prediction(prediction)
    predict = predict_values_warp if fast else predict_values
    values: dict[str, np.ndarray] = {}
    for a in attributes:
        v, _ = residuals[a.name]
        normal_mode = extra_bytes[a.name][0] if a.codec == NORMAL else None
        if prediction is None:                            # a point cloud: sorted, running sums
            values[a.name] = _wrap32(np.cumsum(v, axis=0)) if normal_mode in (None, DIFF) else v
        elif a.codec == NORMAL and normal_mode != DIFF:
            values[a.name] = v
        else:
            values[a.name] = predict(v, prediction, parallelogram=bool(a.strategy & PARALLEL) and a.codec != NORMAL)
    mesh = CortoMesh(np.zeros((nvert, 3), np.float32), faces, groups=groups, exif=exif)
    for a in attributes:
        v = values[a.name]
        if a.codec == NORMAL:
            mesh.normals = _normals(a, v, residuals[a.name][1], extra_bytes[a.name][0], values, faces, nvert)
        elif a.codec == COLOR:
            mesh.colors = _colors(v, extra_bytes[a.name], a.components)
        else:
            out = v.astype(np.float32) * np.float32(a.q)
            if TYPES[a.type] not in ("float", "double"):       # integer outputs: times q, truncated
                out = np.trunc(out).astype(np.int64)
            if a.name == "position":
                mesh.positions = out.astype(np.float32).reshape(nvert, 3)
            elif a.name == "uv":
                mesh.uvs = out.astype(np.float32)
            else:
                mesh.extra[a.name] = out
    if not any(a.name == "position" for a in attributes):
        raise CortoError("the mesh has no position attribute")
    return mesh


def _normals(a: _Attribute, v: np.ndarray, read: int, mode: int, values: dict, faces: np.ndarray,
             nvert: int) -> np.ndarray:
    unit = int(a.q)
    if mode == DIFF or len(faces) == 0:
        return _sphere_from_octa(v, unit)
    if mode not in (ESTIMATED, BORDER):
        raise CortoError(f"normal prediction {mode} is none of Corto's: corrupt")
    if "position" not in values:
        raise CortoError("estimated normals without a position attribute: corrupt")
    estimated = _estimated_normals(values["position"], faces, nvert)
    corrected = np.ones(nvert, bool) if mode == ESTIMATED else _boundary(faces, nvert)
    if int(corrected.sum()) != read and mode == BORDER:
        raise CortoError(f"{read} normal corrections for {int(corrected.sum())} boundary vertices: corrupt")
    out = np.empty((nvert, 3), np.float32)
    e = estimated[corrected]
    out[corrected] = _sphere_from_octa(_octa_from_normals(e, unit) + v[:int(corrected.sum())], unit)
    rest = estimated[~corrected]
    norm = np.sqrt((rest * rest).sum(1, dtype=np.float32))
    with np.errstate(invalid="ignore", divide="ignore"):
        out[~corrected] = rest / norm[:, None]
    return out
