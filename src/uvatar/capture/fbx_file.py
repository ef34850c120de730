"""Autodesk FBX files as a tree of nodes: binary (versions 7.0-7.7: 32-bit record offsets before 7.5,
64-bit after) and ASCII (6.1 and 7.x), read into the same :class:`FbxNode` tree; the owner of FBX's
file layout (:mod:`uvatar.capture.mesh_fbx` reads the scene in it).

Binary: ``Kaydara FBX Binary  \\0``, ``\\x1a\\x00``, the version (uint32); then node records, each its
end offset, property count, property bytes, name; its properties (``Y`` int16, ``C`` bool, ``I``
int32, ``F`` float32, ``D`` float64, ``L`` int64; ``f d l i b`` arrays, raw or zlib-deflated; ``S``
string, ``R`` raw bytes); its children, closed by an empty record. ASCII: ``Name: value, value {`` ...
``}`` lines, arrays as ``*N { a: v, v, ... }``, ``;`` comments. A binary name's ``name\\0\\1Class`` is
ASCII's ``Class::name``; both come out as ``Class::name``. :func:`fbx_bytes` writes a tree as binary
FBX 7.4 (arrays deflated, the footer the FBX SDK writes).
"""

from __future__ import annotations

import re
import zlib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from uvatar.errors import InputError

__all__ = ["FbxNode", "read_fbx", "fbx_bytes", "BINARY_MAGIC"]

BINARY_MAGIC = b"Kaydara FBX Binary  \x00"
SCALARS = {ord("Y"): "<i2", ord("C"): "u1", ord("I"): "<i4", ord("F"): "<f4", ord("D"): "<f8", ord("L"): "<i8"}
ARRAYS = {ord("f"): "<f4", ord("d"): "<f8", ord("l"): "<i8", ord("i"): "<i4", ord("b"): "u1", ord("c"): "u1"}
MAX_DEPTH = 64


@dataclass
class FbxNode:
    """One record: ``name``, ``props`` (ints, floats, str, bytes or numpy arrays) and ``children``."""

    name: str
    props: list = field(default_factory=list)
    children: list[FbxNode] = field(default_factory=list)

    def find(self, name: str) -> FbxNode | None:
        """The first child called ``name``."""
        return next((c for c in self.children if c.name == name), None)

    def find_all(self, name: str) -> list[FbxNode]:
        return [c for c in self.children if c.name == name]

    def value(self, name: str, default=None):
        """The first property of the first child called ``name`` (``default`` where there is none)."""
        child = self.find(name)
        return child.props[0] if child is not None and child.props else default

    def array(self, name: str, dtype) -> np.ndarray | None:
        """The values of the first child called ``name`` as one array (binary's array property, ASCII's
        ``*N { a: ... }`` or FBX 6's plain list); None where there is no such child."""
        child = self.find(name)
        if child is None:
            return None
        if len(child.props) == 1 and isinstance(child.props[0], np.ndarray):
            return child.props[0].astype(dtype, copy=False)
        return np.asarray(child.props, dtype)

    def properties70(self) -> dict[str, list]:
        """A ``Properties70`` (or FBX 6's ``Properties60``) child as {name: its values after the type
        fields}: ``P: "Lcl Translation", "Lcl Translation", "", "A", x, y, z`` gives [x, y, z]."""
        out: dict[str, list] = {}
        for block, skip in (("Properties70", 4), ("Properties60", 3)):
            props = self.find(block)
            for p in props.children if props is not None else ():
                if p.props and isinstance(p.props[0], str):
                    out[p.props[0]] = p.props[skip:]
        return out


class _Binary:
    def __init__(self, path: Path, data: bytes):
        self.path, self.data = path, data
        if len(data) < 27 or data[21:23] != b"\x1a\x00":
            raise InputError(path, "not an FBX file (its binary header is cut)")
        self.version = int.from_bytes(data[23:27], "little")
        if not 7000 <= self.version < 8000:
            raise InputError(path, f"FBX version {self.version / 1000:.1f} is not read (uvatar reads binary 7.x, "
                                   "ASCII 6.1 and 7.x)")
        self.wide = self.version >= 7500
        self.header = 25 if self.wide else 13

    def fail(self, what: str) -> InputError:
        return InputError(self.path, f"FBX file is cut or corrupt ({what})")

    def _uints(self, pos: int, count: int) -> tuple[int, ...]:
        size = 8 if self.wide else 4
        if pos + count * size > len(self.data):
            raise self.fail(f"a record header past the end at byte {pos}")
        return tuple(int.from_bytes(self.data[pos + i * size:pos + (i + 1) * size], "little") for i in range(count))

    def nodes(self, pos: int, end: int, depth: int = 0) -> tuple[list[FbxNode], int]:
        """The records from ``pos`` up to an empty record (or ``end``), and the position after."""
        if depth > MAX_DEPTH:
            raise self.fail("records nested too deep")
        out = []
        while pos + self.header <= end:
            node_end, n_props, props_len = self._uints(pos, 3)
            name_len = self.data[pos + self.header - 1]
            if node_end == 0:                                   # the empty record closing a list
                return out, pos + self.header
            if not pos < node_end <= len(self.data):
                raise self.fail(f"a record ends at byte {node_end}, outside the file")
            start = pos + self.header
            name = self.data[start:start + name_len].decode("latin-1")
            ppos = start + name_len
            props, ppos = self._props(ppos, n_props, ppos + props_len)
            children, _ = self.nodes(ppos, node_end, depth + 1) if ppos < node_end else ([], ppos)
            out.append(FbxNode(name, props, children))
            pos = node_end
        return out, pos

    def _props(self, pos: int, count: int, end: int) -> tuple[list, int]:
        data, props = self.data, []
        for _ in range(count):
            if pos >= end or end > len(data):
                raise self.fail("a property past its record")
            code = data[pos]
            pos += 1
            if code in SCALARS:
                dtype = np.dtype(SCALARS[code])
                value = np.frombuffer(data, dtype, 1, pos)[0].item()
                props.append(bool(value) if code == ord("C") else value)
                pos += dtype.itemsize
            elif code in ARRAYS:
                length, encoding, stored = (int.from_bytes(data[pos + 4 * i:pos + 4 * i + 4], "little") for i in range(3))
                pos += 12
                raw = data[pos:pos + stored]
                if len(raw) != stored:
                    raise self.fail("an array past the end")
                if encoding == 1:
                    try:
                        raw = zlib.decompress(raw)
                    except zlib.error:
                        raise self.fail("a deflated array does not inflate") from None
                elif encoding != 0:
                    raise self.fail(f"an array in unknown encoding {encoding}")
                dtype = np.dtype(ARRAYS[code])
                if len(raw) != length * dtype.itemsize:
                    raise self.fail(f"an array of {length} values holds {len(raw)} bytes")
                props.append(np.frombuffer(raw, dtype).copy())
                pos += stored
            elif code in (ord("S"), ord("R")):
                n = int.from_bytes(data[pos:pos + 4], "little")
                raw = bytes(data[pos + 4:pos + 4 + n])
                if len(raw) != n:
                    raise self.fail("a string past the end")
                pos += 4 + n
                if code == ord("S"):
                    text = raw.decode("utf-8", "replace")
                    if "\x00\x01" in text:                      # binary "name\0\1Class" is ASCII "Class::name"
                        obj, cls = text.split("\x00\x01", 1)
                        text = f"{cls}::{obj}"
                    props.append(text)
                else:
                    props.append(raw)
            else:
                raise self.fail(f"an unknown property type {code!r} at byte {pos - 1}")
        return props, pos


_SKIP = re.compile(rb"(?:\s+|;[^\n]*)*")
_NAME = re.compile(rb"([A-Za-z_][\w|\-]*)[ \t]*:")
_NUMBERS = re.compile(rb"[-+]?[0-9.][0-9.eE+\-]*(?:[ \t]*,\s*[-+]?[0-9.][0-9.eE+\-]*)*")
_STRING = re.compile(rb'"([^"]*)"')
_WORD = re.compile(rb"[^\s{},;:\"]+")
ARRAY_RUN = 16          # a run of more numbers than this is one array (FBX 6's Vertices: 1,2,3,...)


def _numbers(path: Path, text: bytes, pos: int) -> list:
    """A run of comma-separated numbers (at byte ``pos``): one array when long, else each a value."""
    is_float = any(c in text for c in b".eE")
    try:
        values = np.array(text.replace(b"\n", b" ").split(b","), np.float64 if is_float else np.int64)
    except ValueError:
        raise InputError(path, f"ASCII FBX has a number it cannot read at byte {pos}") from None
    if len(values) > ARRAY_RUN:
        return [values]
    return values.tolist()


def _ascii(path: Path, data: bytes) -> list[FbxNode]:
    """The ASCII file's top-level records."""
    root = FbxNode("")
    stack, pos, n = [root], 0, len(data)
    while True:
        pos = _SKIP.match(data, pos).end()
        if pos >= n:
            break
        if data[pos:pos + 1] == b"}":
            if len(stack) == 1:
                raise InputError(path, f"ASCII FBX closes a block it never opened at byte {pos}")
            _flatten_array(stack.pop())
            pos += 1
            continue
        m = _NAME.match(data, pos)
        if m is None:
            raise InputError(path, f"ASCII FBX has text it cannot read at byte {pos} "
                                   f"({data[pos:pos + 24].decode('latin-1')!r})")
        node = FbxNode(m.group(1).decode("latin-1"))
        stack[-1].children.append(node)
        pos = m.end()
        while True:                                      # the record's values, comma-separated
            pos = _SKIP.match(data, pos).end()
            c = data[pos:pos + 1]
            if c == b"{":
                stack.append(node)
                pos += 1
                break
            if c in (b"}", b""):
                break
            if c == b",":                                # an empty value (``Content: , "..."``)
                pos += 1
                continue
            if c == b'"':
                m = _STRING.match(data, pos)
                if m is None:
                    raise InputError(path, f"ASCII FBX has a string that never ends at byte {pos}")
                node.props.append(m.group(1).decode("utf-8", "replace"))
            elif c in b"-+.0123456789":
                m = _NUMBERS.match(data, pos)
                if m is None:
                    raise InputError(path, f"ASCII FBX has a number it cannot read at byte {pos}")
                node.props.extend(_numbers(path, m.group(0), pos))
            elif _NAME.match(data, pos):
                break                                    # the next record
            else:
                m = _WORD.match(data, pos)
                if m is None:
                    raise InputError(path, f"ASCII FBX has text it cannot read at byte {pos}")
                node.props.append(m.group(0).decode("latin-1"))
            pos = m.end()
            after = _SKIP.match(data, pos).end()
            if data[after:after + 1] == b",":
                pos = after + 1
            elif data[after:after + 1] != b"{":
                break
    if len(stack) > 1:
        raise InputError(path, f"ASCII FBX is cut: block {stack[-1].name!r} is never closed")
    return root.children


def _flatten_array(block: FbxNode) -> None:
    """ASCII 7.x's ``Name: *N { a: v, ... }``: the record's values become one array, as binary's."""
    if block.props and isinstance(block.props[0], str) and block.props[0].startswith("*"):
        a = block.find("a")
        values = a.props if a is not None else []
        if len(values) == 1 and isinstance(values[0], np.ndarray):
            block.props = [values[0]]
        else:
            block.props = [np.asarray(values, np.float64 if any(isinstance(v, float) for v in values) else np.int64)]
        block.children = [c for c in block.children if c.name != "a"]


def read_fbx(path: str | Path) -> tuple[list[FbxNode], int]:
    """(the file's top-level records, its version x 1000: 7400 for 7.4; 0 for ASCII where it does not
    say); InputError naming the file where it is not FBX or is cut."""
    path = Path(path)
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror})") from None
    if data.startswith(BINARY_MAGIC):
        reader = _Binary(path, data)
        nodes, _ = reader.nodes(27, len(data))
        return nodes, reader.version
    head = data[:4096].lstrip()
    if not (head.startswith(b";") or b"FBXHeaderExtension" in head or b"FBXVersion" in head):
        raise InputError(path, "not an FBX file (neither the binary header nor ASCII FBX)")
    nodes = _ascii(path, data)
    version = 0
    header = next((n for n in nodes if n.name == "FBXHeaderExtension"), None)
    if header is not None and isinstance(header.value("FBXVersion"), int):
        version = header.value("FBXVersion")
    return nodes, version


# ---- writing (binary 7.4)

FOOTER_ID = bytes.fromhex("fabcab09d0c8d466b176fb831cf7267e")
FOOTER_MAGIC = bytes.fromhex("f85a8c6adef5d97eece90ce3758f290b")
WRITE_VERSION = 7400
DEFLATE_OVER = 128          # arrays of more bytes than this are written deflated


def _prop_bytes(value) -> bytes:
    import struct

    if isinstance(value, (bool, np.bool_)):
        return b"C" + bytes([bool(value)])
    if isinstance(value, np.integer):               # the width asked for: ids are int64 ("L")
        code = {2: b"Y", 4: b"I", 8: b"L"}[value.dtype.itemsize]
        return code + value.astype(value.dtype.newbyteorder("<")).tobytes()
    if isinstance(value, int):
        return (b"I" + struct.pack("<i", value)) if -2**31 <= value < 2**31 else (b"L" + struct.pack("<q", value))
    if isinstance(value, float):
        return b"D" + struct.pack("<d", value)
    if isinstance(value, str):
        if "::" in value and value.split("::", 1)[0].isalpha():      # "Class::name" is binary "name\0\1Class"
            cls, name = value.split("::", 1)
            value = f"{name}\x00\x01{cls}"
        raw = value.encode("utf-8")
        return b"S" + struct.pack("<I", len(raw)) + raw
    if isinstance(value, bytes):
        return b"R" + struct.pack("<I", len(value)) + value
    if isinstance(value, np.ndarray):
        code = {np.dtype("<f4"): b"f", np.dtype("<f8"): b"d", np.dtype("<i4"): b"i", np.dtype("<i8"): b"l",
                np.dtype("u1"): b"b"}[value.dtype.newbyteorder("<") if value.dtype.byteorder == ">" else value.dtype]
        raw = np.ascontiguousarray(value).astype(value.dtype.newbyteorder("<"), copy=False).tobytes()
        encoding = 0
        if len(raw) > DEFLATE_OVER:
            raw, encoding = zlib.compress(raw, 6), 1
        return code + struct.pack("<III", value.size, encoding, len(raw)) + raw
    raise TypeError(f"an FBX property cannot hold {type(value).__name__}")


def _record(node: FbxNode, offset: int) -> bytes:
    """``node`` as a 32-bit-offset record starting at byte ``offset`` (FBX 7.4)."""
    import struct

    props = b"".join(_prop_bytes(p) for p in node.props)
    name = node.name.encode("latin-1")
    head_len = 13 + len(name)
    body, pos = b"", offset + head_len + len(props)
    for child in node.children:
        rec = _record(child, pos)
        body += rec
        pos += len(rec)
    if node.children or not node.props:
        body += b"\x00" * 13
    end = offset + head_len + len(props) + len(body)
    return struct.pack("<III", end, len(node.props), len(props)) + bytes([len(name)]) + name + props + body


def fbx_bytes(nodes: list[FbxNode]) -> bytes:
    """A binary FBX 7.4 file of the top-level records ``nodes`` (names ``Class::name`` as the reader
    gives them), with the empty record, footer and magic that close one."""
    import struct

    out = BINARY_MAGIC + b"\x1a\x00" + struct.pack("<I", WRITE_VERSION)
    for node in nodes:
        out += _record(node, len(out))
    out += b"\x00" * 13 + FOOTER_ID
    out += b"\x00" * ((16 - len(out) % 16) % 16 or 16)
    return out + b"\x00" * 4 + struct.pack("<I", WRITE_VERSION) + b"\x00" * 120 + FOOTER_MAGIC
