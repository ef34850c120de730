"""Garment drape (direction + crease bridging) and tangential cloth drift of the synthetic studio:
known answers on simple surfaces, zero drift at rest, and a ground truth that stays exact."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.capture.synth.config import preset
from uvatar.capture.synth.drape import garment_frame
from uvatar.capture.synth.drift import DRIFT_SLOTS, apply_drift, drift_vectors
from uvatar.geometry import gaussian_surface_matrix


def _sphere(radius=0.1, subdivisions=4):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    v = np.asarray(m.vertices, np.float64)
    return v, v / np.linalg.norm(v, axis=1, keepdims=True)


def test_without_drape_the_garment_normal_is_the_body_normal():
    v, n = _sphere()
    ng, bridge = garment_frame(v, n, None, 0.8, 0.02)
    assert np.array_equal(ng, n) and not bridge.any()
    assert gaussian_surface_matrix(v, n, 0.0) is None


def test_sphere_keeps_its_normals_and_bridges_nothing():
    v, n = _sphere()
    G = gaussian_surface_matrix(v, n, 0.02)
    np.testing.assert_allclose(np.asarray(G.sum(axis=1)).ravel(), 1.0, atol=1e-12)
    ng, bridge = garment_frame(v, n, G, 0.8, 0.02)
    assert np.degrees(np.arccos(np.clip((ng * n).sum(1), -1, 1))).max() < 2.0  # symmetric: same normal
    assert not bridge.any()                                                    # convex: nothing to span


def test_a_crease_is_bridged_and_its_normals_tilt_toward_the_bisector():
    # an inward crease: two half-planes z = 0.5 |x| (normals tilted toward the crease line x = 0)
    x, y = np.meshgrid(np.linspace(-0.1, 0.1, 81), np.linspace(-0.05, 0.05, 41))
    v = np.stack([x.ravel(), y.ravel(), 0.5 * np.abs(x.ravel())], 1)
    n = np.stack([-0.5 * np.sign(x.ravel()), np.zeros(x.size), np.ones(x.size)], 1)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    ng, bridge = garment_frame(v, n, gaussian_surface_matrix(v, n, 0.01), 1.0, 0.05)
    crease = (np.abs(v[:, 0]) < 1e-9) & (np.abs(v[:, 1]) < 0.02)
    flat = (np.abs(v[:, 0]) > 0.05) & (np.abs(v[:, 1]) < 0.02)
    assert bridge[crease].min() > 1e-3 and bridge[flat].max() < 1e-9
    assert ng[crease][:, 2].min() > np.cos(np.radians(6))   # the bisector (up to the voxel sampling)
    near = (np.abs(np.abs(v[:, 0]) - 0.01) < 1e-9) & (np.abs(v[:, 1]) < 0.02)
    assert ((ng[near] * n[near]).sum(1) < np.cos(np.radians(3))).all()        # tilted off the body normal


def test_facing_surfaces_are_not_averaged():
    # two parallel sheets 1 cm apart facing each other (inner thighs): no mixing of their normals
    x, y = np.meshgrid(np.linspace(0, 0.1, 21), np.linspace(0, 0.1, 21))
    a = np.stack([x.ravel(), y.ravel(), np.zeros(x.size)], 1)
    v = np.concatenate([a, a + [0, 0, 0.01]])
    n = np.concatenate([np.tile([0, 0, 1.0], (len(a), 1)), np.tile([0, 0, -1.0], (len(a), 1))])
    ng, _ = garment_frame(v, n, gaussian_surface_matrix(v, n, 0.02), 0.8, 0.02)
    np.testing.assert_allclose(ng, n, atol=1e-12)


@pytest.fixture(scope="module")
def studio(tmp_path_factory):
    from uvatar.capture.synth.pipeline import synthesize

    root = tmp_path_factory.mktemp("drape") / "cap"
    cfg = preset("quick", frames=3, cameras=0, scan_texture=64, gt_texels=64, seed=2, preview=False, scan_noise=0.0)
    synthesize(root, cfg, progress=False)
    from uvatar.capture.synth.gtmaps import GtRenderer

    return root, GtRenderer(root, 64).studio


def test_drift_is_zero_at_rest_and_tangential_and_toward_the_bent_joint(studio):
    _, st = studio
    t, sj = st.template, st.body.semantic_joints
    assert not drift_vectors(t.rest_joints, sj, st.rest_bends, st.rest_bends).any()
    rest = st.posed(np.zeros((st.body.num_joints, 3)), np.zeros(3), np.zeros(3))
    assert not rest.drift.any()
    g = st.gt
    assert g.drift.shape == (len(g.cloth), len(DRIFT_SLOTS)) and g.drift.min() >= 0
    c = st.cfg.clothing
    assert g.drift.max() <= max(c.drift_elbow, c.drift_knee) + 1e-9 and g.drift.max() > 0.5 * c.drift_knee
    # a fully bent left knee: trouser points slide toward the knee along the posed bones, tangentially
    bends = st.rest_bends.copy()
    from uvatar.capture.synth.bends import BENDS

    bends[BENDS.index("l_knee")] = 1.0
    vec = drift_vectors(t.rest_joints, sj, bends, st.rest_bends)
    moving = [i for i, (slot, _) in enumerate(DRIFT_SLOTS) if slot == "l_knee"]
    assert set(np.flatnonzero(np.linalg.norm(vec, axis=1) > 0)) == set(moving)
    _, normals = st.clothed(g, rest)
    d = apply_drift(g.drift, vec, normals)
    np.testing.assert_allclose((d * normals).sum(1), 0.0, atol=1e-12)
    big = np.linalg.norm(d, axis=1) > 1e-3
    assert big.sum() > 10
    # each moving point slides along its bone toward the knee: down the thigh, up the shin
    bone = vec[moving][np.argmax(g.drift[:, moving], axis=1)]
    assert ((d * bone).sum(1)[big] > 0.5 * np.linalg.norm(d[big], axis=1)).all()


def test_scan_vertices_are_the_clothed_surface_of_their_body_origins(studio):
    """Noise-free scan vertices equal Studio.clothed at their body origins (the same function as the
    gt texels), and the stored gt surface lies on the scan mesh."""
    from uvatar.avh.bake.correspond import match_texels
    from uvatar.avh.bake.register import ScanSurface
    from uvatar.capture.meshio import read_mesh
    from uvatar.capture.synth.gtmaps import GtRenderer

    root, st = studio
    import json

    info = json.loads((root / "gt" / "info.json").read_text())
    frame = "000001"
    seg = next(i for i, s in enumerate(info["segments"]) if s["first"] <= 1 <= s["last"])
    topo, vert, *_ = st.segment(seg)
    with np.load(root / "gt" / "frames" / f"{frame}.npz") as z:
        posed = st.posed(z["pose"], z["Rh"], z["Th"])
        surface, mask = z["surface"], z["mask"]
    scan = read_mesh(root / "scans" / f"{frame}.obj")
    expected, _ = st.clothed(vert, posed)
    np.testing.assert_allclose(scan.vertices, expected, atol=2e-6)
    g = GtRenderer(root, 64).render(frame)
    np.testing.assert_allclose(g["surface"][mask], surface[mask], atol=1e-5)
    # distance from each true texel point to the scan along the offset direction (both ways)
    m = match_texels(g["surface"][mask], g["normal"][mask], ScanSurface.build(scan.vertices, scan.faces),
                     True, 2.0, 0.02)
    assert m.hit.mean() > 0.97
    assert np.median(m.distance[m.hit]) < 1e-3        # the decimated scan hugs the exact surface


def test_captures_made_before_the_drape_keep_their_ground_truth():
    from uvatar.capture.synth.gtmaps import config_from_dict

    old = preset("quick").to_dict()
    for key in ("bending_length", "drape_normal_dot", "bridge", "max_bridge", "drift_elbow", "drift_knee",
                "drift_length"):
        old["clothing"].pop(key)
    c = config_from_dict(old).clothing
    assert c.bending_length == 0 and c.drift_elbow == 0 and c.drift_knee == 0
    assert config_from_dict(preset("quick").to_dict()).clothing == preset("quick").clothing
