"""Test helper: an FBX node tree written as ASCII FBX 7.x (what Maya's and the FBX SDK's ASCII writer
make: ``Name: values {`` blocks, arrays as ``*N { a: ... }``, raw bytes in base64), to check the ASCII
reader against the binary one on the same scene."""

from __future__ import annotations

import base64

import numpy as np


def _value(v) -> str:
    if isinstance(v, bool):
        return "T" if v else "F"
    if isinstance(v, bytes):
        return '"' + base64.b64encode(v).decode() + '"'
    if isinstance(v, str):
        return '"' + v + '"'
    if isinstance(v, float):
        return repr(v)
    return str(v)


def _node(node, depth: int) -> list[str]:
    pad = "\t" * depth
    arrays = [p for p in node.props if isinstance(p, np.ndarray)]
    if arrays:
        values = arrays[0]
        text = ",".join(repr(float(x)) if values.dtype.kind == "f" else str(int(x)) for x in values)
        return [f"{pad}{node.name}: *{len(values)} {{", f"{pad}\ta: {text}", f"{pad}}}"]
    head = f"{pad}{node.name}: " + ", ".join(_value(p) for p in node.props)
    if not node.children:
        return [head.rstrip()]
    lines = [head.rstrip() + " {"]
    for child in node.children:
        lines += _node(child, depth + 1)
    return lines + [f"{pad}}}"]


def ascii_fbx(nodes, version: int = 7400) -> str:
    lines = [f"; FBX {version // 1000}.{version % 1000 // 100}.0 project file", "; written by uvatar's tests", ""]
    for node in nodes:
        lines += _node(node, 0)
    return "\n".join(lines) + "\n"
