"""Texel sampling, normals, tangent frames and texture lookups: analytic answers, numpy/torch parity,
float64 gradcheck."""

import numpy as np
import pytest
import torch

from uvatar.errors import InputError
from uvatar.geometry import (
    face_normals,
    rasterize_uv,
    sample_texture,
    sample_vertex_attribute,
    texel_normals,
    texel_positions,
    texel_tangent_frames,
    texel_uv,
    vertex_normals,
)
from uvatar.geometry.uv_raster import UVRaster


def plane(n=4, mirror=False):
    """Flat grid in z = 0 over [0,1]^2 with uv = (x, y) (or (1 - x, y) when mirrored)."""
    ys, xs = np.mgrid[0 : n + 1, 0 : n + 1]
    uv = np.stack([xs.ravel(), ys.ravel()], 1).astype(np.float64) / n
    verts = np.concatenate([uv, np.zeros((len(uv), 1))], 1)
    if mirror:
        uv = uv.copy()
        uv[:, 0] = 1 - uv[:, 0]
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    a, b, c, d = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel(), idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.concatenate([np.stack([a, b, d], 1), np.stack([a, d, c], 1)])
    return verts, faces, uv


def sphere_with_uv(subdiv=2):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdiv)
    v = np.asarray(m.vertices)
    f = np.asarray(m.faces)
    # per-face UV islands: each face its own small triangle in an atlas (exercises seams everywhere)
    k = int(np.ceil(np.sqrt(len(f))))
    cell = np.stack(np.divmod(np.arange(len(f)), k), 1)[:, ::-1] / k
    corner = np.array([[0.1, 0.1], [0.9, 0.1], [0.1, 0.9]]) / k
    uvs = (cell[:, None, :] + corner[None]).reshape(-1, 2)
    uv_faces = np.arange(3 * len(f)).reshape(-1, 3)
    return v, f, uvs, uv_faces


def test_positions_on_plane_equal_texel_uv():
    v, f, uv = plane()
    r = rasterize_uv(uv, f, 32)
    p = texel_positions(r, f, v)
    assert r.mask.all()
    np.testing.assert_allclose(p[..., :2], texel_uv(32), atol=1e-6)
    p5 = texel_positions(r, f, f, uv, v)  # the 5-argument form of the contract
    np.testing.assert_array_equal(p, p5)


def test_sample_batched_numpy_torch_parity_and_zero_outside():
    v, f, uvs, uvf = sphere_with_uv(1)
    r = rasterize_uv(uvs, uvf, 48)
    attr = np.random.default_rng(0).normal(size=(2, 3, len(v), 4))
    out = sample_vertex_attribute(r, f, attr)
    assert out.shape == (2, 3, 48, 48, 4)
    assert np.all(out[..., ~r.mask, :] == 0)
    out_t = sample_vertex_attribute(r, f, torch.from_numpy(attr))
    np.testing.assert_allclose(out_t.numpy(), out, atol=1e-12)
    # one texel by hand
    i, j = np.argwhere(r.mask)[5]
    expect = (attr[1, 2][f[r.face_index[i, j]]] * r.bary[i, j][:, None]).sum(0)
    np.testing.assert_allclose(out[1, 2, i, j], expect, atol=1e-6)


def test_sample_vertex_attribute_gradcheck():
    v, f, uv = plane(2)
    r = rasterize_uv(uv, f, 6)
    attr = torch.randn(len(v), 2, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda a: sample_vertex_attribute(r, f, a), (attr,))


def test_texel_normals_plane_and_sphere():
    v, f, uv = plane()
    r = rasterize_uv(uv, f, 16)
    np.testing.assert_allclose(texel_normals(r, f, v)[r.mask], np.tile([0, 0, 1.0], (r.num_valid, 1)),
                               atol=1e-12)
    v, f, uvs, uvf = sphere_with_uv(3)
    r = rasterize_uv(uvs, uvf, 128)
    n = texel_normals(r, f, v)[r.mask]
    p = texel_positions(r, f, v)[r.mask]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1, atol=1e-6)
    assert (n * p / np.linalg.norm(p, axis=1, keepdims=True)).sum(1).min() > 0.99


def test_face_and_vertex_normals_area_weighted():
    # two faces sharing vertex 0: a big one in z=0 (normal +z) and a small one in x=0 (normal +x)
    v = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0], [0, 0.0, 1], [0, 0.5, 0]], dtype=np.float64)
    f = np.array([[0, 1, 2], [0, 4, 3]])
    np.testing.assert_allclose(face_normals(v, f), [[0, 0, 1], [1, 0, 0]], atol=1e-12)
    n0 = vertex_normals(v, f)[0]
    expect = np.array([0.25, 0, 2.0])  # area 0.25 (x) vs 2 (z)
    np.testing.assert_allclose(n0, expect / np.linalg.norm(expect), atol=1e-12)
    vt = torch.tensor(np.stack([v, v * 2]), requires_grad=True)
    nt = vertex_normals(vt, f)
    np.testing.assert_allclose(nt[1].detach().numpy(), vertex_normals(v, f), atol=1e-12)
    np.testing.assert_allclose(face_normals(vt, f)[0].detach().numpy(), face_normals(v, f), atol=1e-12)
    nt.sum().backward()
    assert vt.grad is not None and torch.isfinite(vt.grad).all()


def test_vertex_normals_gradcheck():
    v, f, _, _ = sphere_with_uv(0)
    vt = torch.tensor(v[:12] * 1.1, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: vertex_normals(x, f), (vt,))


@pytest.mark.parametrize("mirror, follow", [(False, False), (True, False), (True, True)])
def test_tangent_frames_plane(mirror, follow):
    v, f, uv = plane(mirror=mirror)
    r = rasterize_uv(uv, f, 16)
    fr = texel_tangent_frames(r, f, f, uv, v, follow_mirroring=follow)
    assert fr.shape == (16, 16, 3, 3)
    t, b, n = fr[..., 0], fr[..., 1], fr[..., 2]
    sx = -1.0 if mirror else 1.0  # tangent follows dP/du
    sy = -1.0 if mirror and not follow else 1.0  # bitangent: n x t, or dP/dv when following mirrors
    np.testing.assert_allclose(t[r.mask], np.tile([sx, 0, 0], (r.num_valid, 1)), atol=1e-12)
    np.testing.assert_allclose(b[r.mask], np.tile([0, sy, 0], (r.num_valid, 1)), atol=1e-12)
    np.testing.assert_allclose(n[r.mask], np.tile([0, 0, 1.0], (r.num_valid, 1)), atol=1e-12)
    np.testing.assert_allclose(np.linalg.det(fr[r.mask]), sx * sy)


def test_tangent_frames_sphere_orthonormal_torch_parity():
    v, f, uvs, uvf = sphere_with_uv(2)
    r = rasterize_uv(uvs, uvf, 64)
    fr = texel_tangent_frames(r, f, uvf, uvs, v)
    m = fr[r.mask]
    np.testing.assert_allclose(np.einsum("nji,njk->nik", m, m), np.broadcast_to(np.eye(3), m.shape), atol=1e-9)
    np.testing.assert_allclose(np.linalg.det(m), 1.0, atol=1e-9)  # proper rotations
    np.testing.assert_allclose(fr[~r.mask], np.broadcast_to(np.eye(3), fr[~r.mask].shape))
    vt = torch.tensor(np.stack([v, v]), requires_grad=True)
    frt = texel_tangent_frames(r, f, uvf, uvs, vt)
    assert frt.shape == (2, 64, 64, 3, 3)
    np.testing.assert_allclose(frt[0].detach().numpy(), fr, atol=1e-9)
    frt.sum().backward()
    assert torch.isfinite(vt.grad).all()


def test_sample_texture_known_answers():
    img = np.arange(4 * 5 * 1, dtype=np.float64).reshape(4, 5, 1)
    tuv = np.stack([(np.arange(5) + 0.5) / 5, np.full(5, 1 - 0.5 / 4)], 1)  # centres of row 0
    np.testing.assert_allclose(sample_texture(img, tuv)[:, 0], img[0, :, 0])
    mid = np.array([[1.0 / 5, 1 - 0.5 / 4]])  # halfway between columns 0 and 1 of row 0
    np.testing.assert_allclose(sample_texture(img, mid)[0, 0], 0.5)
    corners = np.array([[0, 0], [1, 1], [-1, 2.0]])  # clamp to edge
    np.testing.assert_allclose(sample_texture(img, corners)[:, 0], [img[3, 0, 0], img[0, 4, 0], img[0, 0, 0]])
    uv = np.random.default_rng(0).uniform(size=(7, 3, 2))
    out = sample_texture(img, uv)
    assert out.shape == (7, 3, 1)
    out_t = sample_texture(torch.from_numpy(img), torch.from_numpy(uv))
    np.testing.assert_allclose(out_t.numpy(), out, atol=1e-12)


def test_sample_texture_gradcheck():
    img = torch.rand(4, 5, 2, dtype=torch.float64, requires_grad=True)
    uv = torch.tensor([[0.31, 0.62], [0.77, 0.13]], dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(sample_texture, (img, uv))


def test_bad_inputs():
    v, f, uv = plane(2)
    r = rasterize_uv(uv, f, 8)
    with pytest.raises(InputError):
        sample_vertex_attribute(r, f, np.zeros(5))
    with pytest.raises(InputError):
        sample_vertex_attribute(r, f, np.zeros((3, 2)))  # too few vertices
    with pytest.raises(InputError):
        sample_texture(np.zeros((4, 4)), np.zeros((1, 2)))
    with pytest.raises(TypeError):
        texel_positions(r, f, f, v)
    assert isinstance(r, UVRaster)


@pytest.mark.gpu
def test_cuda_matches_cpu():
    v, f, uvs, uvf = sphere_with_uv(2)
    r = rasterize_uv(uvs, uvf, 64)
    vt = torch.tensor(np.stack([v, 1.1 * v]), dtype=torch.float32)
    cpu = texel_tangent_frames(r, f, uvf, uvs, vt)
    gpu = texel_tangent_frames(r, f, uvf, uvs, vt.cuda())
    assert gpu.device.type == "cuda"
    np.testing.assert_allclose(gpu.cpu().numpy(), cpu.numpy(), atol=1e-5)
    pos = texel_positions(r, f, vt.cuda())
    np.testing.assert_allclose(pos.cpu().numpy(), texel_positions(r, f, vt).numpy(), atol=1e-6)
    img = torch.rand(8, 8, 3)
    uv = torch.rand(100, 2)
    np.testing.assert_allclose(sample_texture(img.cuda(), uv.cuda()).cpu().numpy(),
                               sample_texture(img, uv).numpy(), atol=1e-6)


def test_tangent_frames_gradcheck():
    v, f, uv = plane(2)
    v[:, 2] = 0.1 * np.sin(3 * v[:, 0]) + 0.05 * v[:, 1] ** 2  # curved, so normals vary
    r = rasterize_uv(uv, f, 4)
    vt = torch.tensor(v, dtype=torch.float64, requires_grad=True)
    assert torch.autograd.gradcheck(lambda x: texel_tangent_frames(r, f, f, uv, x), (vt,))


def test_face_tangents_known_and_degenerate_uv():
    from uvatar.geometry import face_tangents

    v = np.array([[0, 0, 0], [2, 0, 0], [0, 3, 0.0]])
    f = np.array([[0, 1, 2], [0, 1, 2]])
    uvs = np.array([[0, 0], [1, 0], [0, 1.0], [0.5, 0.5]])
    uvf = np.array([[0, 1, 2], [3, 3, 3]])  # second face: all corners share one UV
    t, b = face_tangents(v, f, uvs, uvf)
    np.testing.assert_allclose(t, [[2, 0, 0], [2, 0, 0]])  # dP/du; degenerate: first edge
    np.testing.assert_allclose(b, [[0, 3, 0], [0, 0, 0]])  # dP/dv; degenerate: zero
