"""Kinematic chain and skinning: fast paths against their plain twins, known answers, gradcheck."""

import math

import numpy as np
import pytest
import roma
import torch

from uvatar.body.kinematics import (
    forward_kinematics,
    forward_kinematics_by_level,
    forward_kinematics_doubling,
    forward_kinematics_reference,
    kinematic_levels,
    skin,
    skin_reference,
    skinning_transforms,
)

# a small tree: 0 -> 1 -> 2 -> 3, 0 -> 4 -> 5, 1 -> 6
PARENTS = np.array([-1, 0, 1, 2, 0, 4, 1])


def _rig(batch=3, dtype=torch.float64, seed=0):
    g = torch.Generator().manual_seed(seed)
    J = len(PARENTS)
    rot = roma.rotvec_to_rotmat(torch.randn(batch, J, 3, generator=g, dtype=dtype))
    offsets = torch.randn(1, J, 3, generator=g, dtype=dtype)
    return rot, offsets


@pytest.mark.parametrize("batch", [1, 4])
@pytest.mark.parametrize("way", [forward_kinematics, forward_kinematics_by_level, forward_kinematics_doubling])
def test_forward_kinematics_matches_reference(batch, way):
    rot, offsets = _rig(batch)
    F, p = way(kinematic_levels(PARENTS), rot, offsets)
    F_ref, p_ref = forward_kinematics_reference(PARENTS, rot, offsets)
    torch.testing.assert_close(F, F_ref)
    torch.testing.assert_close(p, p_ref)


def test_forward_kinematics_chooses_by_device_and_batch(monkeypatch):
    """Small CPU batches (and every batch off the CPU) by doubling, large CPU batches by level."""
    import uvatar.body.kinematics as kin

    calls = []
    monkeypatch.setattr(kin, "forward_kinematics_by_level", lambda *a: calls.append("level"))
    monkeypatch.setattr(kin, "forward_kinematics_doubling", lambda *a: calls.append("doubling"))
    levels = kinematic_levels(PARENTS)
    for batch in (1, kin.DOUBLING_MAX_ON_CPU // len(PARENTS), kin.DOUBLING_MAX_ON_CPU // len(PARENTS) + 1):
        kin.forward_kinematics(levels, *_rig(batch))
    assert calls == ["doubling", "doubling", "level"]


def test_forward_kinematics_known_answer():
    # chain 0 -> 1 -> 2 along +X; bend joint 1 by 90 degrees about +Z: joint 2 moves to (1, 1, 0)
    parents = np.array([-1, 0, 1])
    offsets = torch.tensor([[[0.0, 0, 0], [1, 0, 0], [1, 0, 0]]], dtype=torch.float64)
    rv = torch.zeros(1, 3, 3, dtype=torch.float64)
    rv[0, 1] = torch.tensor([0, 0, math.pi / 2])
    F, p = forward_kinematics(kinematic_levels(parents), roma.rotvec_to_rotmat(rv), offsets)
    torch.testing.assert_close(p[0, 2], torch.tensor([1.0, 1.0, 0.0], dtype=torch.float64))
    torch.testing.assert_close(F[0, 2], roma.rotvec_to_rotmat(rv[0, 1]))


def test_kinematic_levels_rejects_two_roots():
    with pytest.raises(ValueError, match="root"):
        kinematic_levels([-1, -1, 0])


def test_kinematic_levels_rejects_a_cycle():
    with pytest.raises(ValueError, match="descend from the root"):
        kinematic_levels([-1, 2, 1])


@pytest.mark.parametrize("depth", [1, 2, 3, 4, 7, 8, 16, 17, 40])
def test_doubling_rounds_cover_every_chain(depth):
    """A chain of ``depth`` levels with a branch at every joint (joints listed children first, so no
    order is assumed): ceil(log2(depth + 1)) doubling rounds, depth + 1 levels, and both ways give the
    frames of the per-joint reference within float64 round-off."""
    chain = list(range(depth + 1))[::-1]                     # chain[i] is at depth i: the root is the last id
    parents = np.full(2 * depth + 1, -1)
    for i in range(1, depth + 1):
        parents[chain[i]] = chain[i - 1]
        parents[depth + i] = chain[i - 1]                    # a leaf beside each chain joint
    levels = kinematic_levels(parents)
    assert levels.depth == depth and len(levels.jumps) == math.ceil(math.log2(depth + 1))
    assert len(levels.levels) == depth + 1
    g = torch.Generator().manual_seed(depth)
    rot = roma.rotvec_to_rotmat(0.5 * torch.randn(2, len(parents), 3, generator=g, dtype=torch.float64))
    offsets = torch.randn(1, len(parents), 3, generator=g, dtype=torch.float64)
    F_ref, p_ref = forward_kinematics_reference(parents, rot, offsets)
    for way in (forward_kinematics_by_level, forward_kinematics_doubling):
        F, p = way(levels, rot, offsets)
        torch.testing.assert_close(F, F_ref, atol=1e-12, rtol=0)
        torch.testing.assert_close(p, p_ref, atol=1e-12, rtol=0)


def test_rotvec_to_rotmat_equals_roma_and_gradcheck():
    """The posing's Rodrigues (torch.sinc) against roma's, from 1e-9 rad to past pi, exactly zero
    included: float64 within 1e-12 (roma is first order below 1e-6 rad), float32 within 1e-6; float64
    gradcheck, at zero too."""
    from uvatar.body.kinematics import rotvec_to_rotmat

    g = torch.Generator().manual_seed(0)
    scales = torch.logspace(-9, 0.6, 500, dtype=torch.float64)[:, None]
    rotvecs = torch.cat([torch.zeros(1, 3, dtype=torch.float64),
                         torch.randn(500, 3, generator=g, dtype=torch.float64) * scales])
    torch.testing.assert_close(rotvec_to_rotmat(rotvecs), roma.rotvec_to_rotmat(rotvecs), atol=1e-12, rtol=0)
    torch.testing.assert_close(rotvec_to_rotmat(rotvecs.float()), roma.rotvec_to_rotmat(rotvecs.float()),
                               atol=1e-6, rtol=0)
    assert rotvec_to_rotmat(rotvecs[1:].reshape(-1, 5, 3)).shape == (100, 5, 3, 3)
    assert torch.autograd.gradcheck(rotvec_to_rotmat, (torch.zeros(2, 3, dtype=torch.float64, requires_grad=True),))
    assert torch.autograd.gradcheck(rotvec_to_rotmat, (rotvecs[-5:].clone().requires_grad_(),))


def test_skin_matches_reference_and_identity():
    rot, offsets = _rig(2)
    F, p = forward_kinematics(kinematic_levels(PARENTS), rot, offsets)
    heads = torch.randn(1, len(PARENTS), 3, dtype=torch.float64)
    T = skinning_transforms(F, p, None, heads)
    g = torch.Generator().manual_seed(1)
    verts = torch.randn(1, 50, 3, generator=g, dtype=torch.float64)
    w = torch.rand(50, len(PARENTS), generator=g, dtype=torch.float64)
    w = w / w.sum(1, keepdim=True)
    torch.testing.assert_close(skin(verts, w, T), skin_reference(verts, w, T))
    # identity transforms leave the mesh in place
    eye = torch.eye(3, 4, dtype=torch.float64).expand(2, len(PARENTS), 3, 4)
    torch.testing.assert_close(skin(verts, w, eye), verts.expand(2, -1, -1))


def test_chain_and_skin_gradcheck_float64():
    _, offsets = _rig(1)
    levels = kinematic_levels(PARENTS)
    heads = torch.randn(1, len(PARENTS), 3, dtype=torch.float64)
    verts = torch.randn(1, 6, 3, dtype=torch.float64)
    w = torch.softmax(torch.randn(6, len(PARENTS), dtype=torch.float64), 1)

    def f(rotvecs):
        F, p = forward_kinematics(levels, roma.rotvec_to_rotmat(rotvecs), offsets)
        return skin(verts, w, skinning_transforms(F, p, None, heads))

    rv = (0.3 * torch.randn(1, len(PARENTS), 3, dtype=torch.float64)).requires_grad_()
    assert torch.autograd.gradcheck(f, (rv,), eps=1e-6, atol=1e-5)


def test_sparse_skin_matches_dense_and_gradcheck():
    from uvatar.body.kinematics import sparse_weights

    g = torch.Generator().manual_seed(3)
    J = len(PARENTS)
    w = torch.rand(40, J, generator=g, dtype=torch.float64)
    w[w < 0.6] = 0
    w[:, 0] += 1e-3
    w = w / w.sum(1, keepdim=True)
    T = torch.randn(2, J, 3, 4, generator=g, dtype=torch.float64)
    verts = torch.randn(1, 40, 3, generator=g, dtype=torch.float64)
    torch.testing.assert_close(skin(verts, sparse_weights(w), T), skin_reference(verts, w, T))
    ws = sparse_weights(w[:6])
    Tg = T[:1].clone().requires_grad_()
    assert torch.autograd.gradcheck(lambda t: skin(verts[:, :6], ws, t), (Tg,), eps=1e-6, atol=1e-5)


def test_vertex_normals_known_answer_and_twin():
    import trimesh

    from uvatar.geometry.frames import vertex_face_adjacency, vertex_normals

    # cube centred at the origin: every corner normal points outward, along its corner
    box = trimesh.creation.box()
    v = torch.as_tensor(box.vertices, dtype=torch.float64)[None].repeat(2, 1, 1)
    f = torch.as_tensor(box.faces, dtype=torch.int64)
    n_fast = vertex_normals(v, f, vertex_face_adjacency(f, v.shape[1]))
    n_ref = vertex_normals(v, f)
    np.testing.assert_allclose(vertex_normals(v.numpy(), f.numpy()), n_ref.numpy(), atol=1e-12)  # numpy twin
    torch.testing.assert_close(n_fast, n_ref)
    expected = torch.sign(v) / math.sqrt(3)
    assert ((n_fast * expected).sum(-1) > 0.5).all()
    torch.testing.assert_close(n_fast.norm(dim=-1), torch.ones(2, 8, dtype=torch.float64))


def test_tree_helpers_known_answer():
    from uvatar.body.kinematics import ancestor_matrix, subtree

    # 0 -> 1 -> 2, 0 -> 3 -> 4; joint 5's parent (4) comes before it, joint 1's child 6 comes last
    parents = [-1, 0, 1, 0, 3, 4, 1]
    anc = ancestor_matrix(parents)
    assert anc[5].nonzero()[0].tolist() == [0, 3, 4, 5] and anc[6].nonzero()[0].tolist() == [0, 1, 6]
    assert subtree(parents, 1).tolist() == [1, 2, 6]
    assert subtree(parents, [1, 4], include_roots=False).tolist() == [2, 5, 6]
    assert subtree(parents, 0).tolist() == list(range(7))


def test_nearest_ancestor_known_answer():
    from uvatar.body.kinematics import nearest_ancestor

    parents = [-1, 0, 1, 0, 3, 4, 1]
    # candidates 1 and 4: joints 1, 2, 6 fall under 1 (position 0), 4 and 5 under 4 (position 1)
    assert nearest_ancestor(parents, [1, 4]).tolist() == [-1, 0, 0, -1, 1, 1, 0]
    # nested candidates: the deepest one wins
    assert nearest_ancestor(parents, [0, 3]).tolist() == [0, 0, 0, 1, 1, 1, 0]
    assert nearest_ancestor(parents, []).tolist() == [-1] * 7
