"""One computation of the faces' cross products for both normals (:func:`uvatar.geometry.frames.mesh_normals`,
what the bake's scan preparation uses)."""

from __future__ import annotations

import numpy as np
import torch


def test_mesh_normals_are_vertex_and_face_normals_bit_for_bit():
    """``mesh_normals`` (one cross product per face for both) equals the two functions, numpy and torch;
    the written-out numpy cross equals ``np.cross``."""
    from uvatar.geometry.frames import _cross_numpy, face_normals, mesh_normals, vertex_normals

    rng = np.random.default_rng(3)
    v = rng.normal(size=(40, 3))
    f = rng.integers(0, 40, size=(70, 3))
    vn, fn = mesh_normals(v, f)
    np.testing.assert_array_equal(vn, vertex_normals(v, f))
    np.testing.assert_array_equal(fn, face_normals(v, f))
    a, b = rng.normal(size=(2, 5, 7, 3))
    np.testing.assert_array_equal(_cross_numpy(a, b), np.cross(a, b))
    vt = torch.from_numpy(v)
    tn, tf = mesh_normals(vt, torch.from_numpy(f))
    torch.testing.assert_close(tn, vertex_normals(vt, torch.from_numpy(f)), rtol=0, atol=0)
    torch.testing.assert_close(tf, face_normals(vt, torch.from_numpy(f)), rtol=0, atol=0)
