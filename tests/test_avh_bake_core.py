"""AVH bake building blocks on analytic meshes: candidate choice, visibility, scores, inpainting,
registration (no body model needed)."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.avh.bake.confidence import (
    distance_score,
    face_visibility,
    face_visibility_reference,
    frames_from_normals,
    hemisphere_directions,
    normal_match_score,
    vertex_visibility,
)
from uvatar.avh.bake.config import BakeConfig, PoseRefineConfig, RegistrationConfig
from uvatar.avh.bake.correspond import choose_candidates, choose_candidates_reference, match_texels
from uvatar.avh.bake.inpaint import inpaint_telea
from uvatar.avh.bake.refine import region_weights, subtree_weights, untracked_skin_weight
from uvatar.avh.bake.register import ScanSurface, register_to_scan, uniform_laplacian_matrix


def icosphere(subdivisions: int = 3, radius: float = 1.0):
    import trimesh

    mesh = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


# -- candidate choice (paper's rule) ----------------------------------------------------------------
def test_choose_candidates_known_cases():
    #            hit+  d+   pos+  hit-  d-   pos-   -> expected side
    cases = [(True, 1.0, True, True, 3.0, True, 1),      # same polarity: nearest (+)
             (True, 3.0, False, True, 1.0, False, -1),   # same polarity: nearest (-)
             (True, 1.9, True, True, 1.0, False, 1),     # mixed: positive within 2x wins
             (True, 2.1, True, True, 1.0, False, -1),    # mixed: positive more than 2x farther loses
             (True, 1.0, False, True, 2.0, True, -1),    # mixed: positive (-) within 2x wins
             (True, 1.0, False, True, 2.5, True, 1),     # mixed: positive (-) beyond 2x loses
             (False, 0.0, False, True, 1.0, False, -1),  # only one candidate
             (True, 5.0, False, False, 0.0, False, 1),
             (False, 0.0, False, False, 0.0, False, 0)]
    cols = list(zip(*cases, strict=True))
    side = choose_candidates(*[np.array(c) for c in cols[:6]])
    np.testing.assert_array_equal(side, cols[6])
    ref = choose_candidates_reference(*[np.array(c) for c in cols[:6]])
    np.testing.assert_array_equal(ref, cols[6])
    # without the polarity rule the nearest always wins
    nearest = choose_candidates(*[np.array(c) for c in cols[:6]], polarity_rule=False)
    assert nearest[2] == -1 and nearest[4] == 1


@pytest.mark.parametrize("polarity_rule", [True, False])
@pytest.mark.parametrize("ratio", [2.0, 1.5])
def test_choose_candidates_parity_with_reference(polarity_rule, ratio):
    rng = np.random.default_rng(0)
    n = 2000
    args = (rng.random(n) < 0.7, rng.random(n), rng.random(n) < 0.5,
            rng.random(n) < 0.7, rng.random(n), rng.random(n) < 0.5)
    np.testing.assert_array_equal(choose_candidates(*args, polarity_rule=polarity_rule, ratio=ratio),
                                  choose_candidates_reference(*args, polarity_rule=polarity_rule, ratio=ratio))


def test_match_texels_on_concentric_spheres():
    v, f = icosphere(4, 1.0)
    n = v / np.linalg.norm(v, axis=1, keepdims=True)
    points = n[:200] * 1.0
    outer = ScanSurface.build(*icosphere(5, 1.01))
    m = match_texels(points, n[:200], outer)
    assert m.hit.all() and (m.side == 1).all() and m.positive.all()
    np.testing.assert_allclose(m.distance, 0.01, atol=1e-3)            # chord error of the sphere
    np.testing.assert_allclose((m.scan_normal * n[:200]).sum(1), 1.0, atol=1e-3)
    inner = ScanSurface.build(*icosphere(5, 0.99))
    m = match_texels(points, n[:200], inner)
    assert (m.side == -1).all() and m.positive.all()
    # a max distance shorter than the gap finds nothing
    assert not match_texels(points, n[:200], inner, max_distance=0.005).hit.any()


def test_match_texels_polarity_rule_prefers_positive_surface():
    """Query on a plane facing +z; a back-facing sheet 1 cm above and a front-facing one 1.5 cm below."""
    from uvatar.avh.bake.register import ScanSurface

    quad = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    up = np.array([[0, 1, 2], [0, 2, 3]])
    down = up[:, ::-1]
    verts = np.concatenate([quad + [0, 0, 0.01], quad + [0, 0, -0.015]])
    faces = np.concatenate([down, up + 4])
    scan = ScanSurface.build(verts, faces)
    p = np.zeros((1, 3))
    nrm = np.array([[0.0, 0.0, 1.0]])
    with_rule = match_texels(p, nrm, scan)
    assert with_rule.side[0] == -1 and with_rule.positive[0]
    np.testing.assert_allclose(with_rule.distance, 0.015, atol=1e-6)
    without = match_texels(p, nrm, scan, polarity_rule=False)
    assert without.side[0] == 1 and not without.positive[0]


# -- confidence terms ------------------------------------------------------------------------------
def test_hemisphere_directions_and_frames():
    d = hemisphere_directions(64)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert (d[:, 2] > 0).all()
    np.testing.assert_allclose(d.mean(0), [0, 0, 0.5], atol=0.03)   # uniform hemisphere: E[z] = 1/2
    rng = np.random.default_rng(1)
    n = rng.normal(size=(50, 3))
    n[0] = [0, 0, -1]
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    fr = frames_from_normals(n)
    np.testing.assert_allclose(np.einsum("nji,njk->nik", fr, fr), np.broadcast_to(np.eye(3), (50, 3, 3)), atol=1e-12)
    np.testing.assert_allclose(fr[:, :, 2], n, atol=1e-12)


def test_visibility_convex_inside_and_parity():
    v, f = icosphere(2)
    outward = face_visibility(v, f)
    np.testing.assert_allclose(outward, 1.0)                        # convex: every ray escapes
    inward = face_visibility(v, f[:, ::-1])
    np.testing.assert_allclose(inward, 0.0)                         # inside a closed surface
    vv = vertex_visibility(v, f)
    assert vv.shape == (len(v),) and np.allclose(vv, 1.0)
    # a sphere beside a plane: partly occluded faces; vectorized == per-face twin
    plane = np.array([[-3, -1.2, -3], [3, -1.2, -3], [3, -1.2, 3], [-3, -1.2, 3]], np.float64)
    verts = np.concatenate([v, plane])
    faces = np.concatenate([f, np.array([[0, 2, 1], [0, 3, 2]]) + len(v)])
    fast = face_visibility(verts, faces, n_rays=32, faces_per_batch=37)
    ref = face_visibility_reference(verts, faces, n_rays=32)
    np.testing.assert_allclose(fast, ref)
    assert fast[: len(f)].min() < 0.9                               # the plane hides part of the sky


def test_distance_and_normal_scores():
    np.testing.assert_allclose(distance_score([0.0, 0.02, 0.04, 1.0, np.inf], 0.04), [1.0, 0.5, 0.0, 0.0, 0.0])
    n = np.array([[0, 0, 1.0]] * 3)
    m = np.array([[0, 0, 1.0], [0, 0, -1.0], [1, 0, 0.0]])
    np.testing.assert_allclose(normal_match_score(n, m), [1.0, 0.0, 0.5])


# -- inpainting --------------------------------------------------------------------------------------
@pytest.mark.parametrize("band", [None, 4])
def test_inpaint_keeps_known_and_fills_smoothly(band):
    r = 64
    y, x = np.mgrid[0:r, 0:r] / r
    image = np.stack([x, y, 0.3 + 0 * x], -1).astype(np.float32)
    fill = np.zeros((r, r), bool)
    fill[20:30, 20:30] = True
    fill[:, 50:] = True
    out = inpaint_telea(np.where(fill[..., None], 0.0, image), fill, radius=3, band=band)
    np.testing.assert_array_equal(out[~fill], image[~fill])
    np.testing.assert_allclose(out[..., 2][fill], 0.3, atol=1e-5)          # constant stays constant
    hole = np.zeros_like(fill)
    hole[20:30, 20:30] = True
    assert np.abs(out[hole] - image[hole]).max() < 0.08                      # a gradient is continued
    assert np.isfinite(out).all()


def test_inpaint_edge_cases():
    img = np.ones((8, 8), np.float32)
    np.testing.assert_array_equal(inpaint_telea(img, np.zeros((8, 8), bool)), img)
    np.testing.assert_array_equal(inpaint_telea(img, np.ones((8, 8), bool)), 0 * img)
    with pytest.raises(ValueError):
        inpaint_telea(img, np.zeros((4, 4), bool))


# -- registration ------------------------------------------------------------------------------------
def test_uniform_laplacian_rows():
    v, f = icosphere(1)
    lap = uniform_laplacian_matrix(f, len(v))
    np.testing.assert_allclose(np.asarray(lap.sum(1)).ravel(), 0.0, atol=1e-12)   # constants -> 0
    np.testing.assert_allclose(lap.diagonal(), 1.0)


def test_registration_pulls_sphere_onto_larger_sphere():
    v, f = icosphere(3, 1.0)
    scan = ScanSurface.build(*icosphere(5, 1.03))
    cfg = RegistrationConfig(stiffness=(30.0, 1.0), iterations=(2, 2), max_distance=(0.05, 0.05),
                             modes=("closest", "normal"))
    x, stats = register_to_scan(v, f, scan, cfg)
    radius = np.linalg.norm(x, axis=1)
    np.testing.assert_allclose(radius, 1.03, atol=2e-3)
    assert stats["matched_fraction"][-1] > 0.99
    # the normal finish never slides: directions stay those of the shadow vertices
    np.testing.assert_allclose(x / radius[:, None], v, atol=2e-3)


def test_registration_config_checks_lengths_and_roundtrip():
    with pytest.raises(ValueError):
        RegistrationConfig(stiffness=(1.0, 2.0), iterations=(1,), max_distance=(0.1, 0.1), modes=("rays", "rays"))
    cfg = BakeConfig().with_updates(texels=128, registration_stiffness=(5.0,), registration_iterations=(1,),
                                    registration_max_distance=(0.02,), registration_modes=("normal",),
                                    pose_refine_iterations=2)
    import json

    again = BakeConfig.from_dict(json.loads(json.dumps(cfg.to_dict())))
    assert again == cfg and again.pose_refine == PoseRefineConfig(iterations=2)
    old = {k: v for k, v in cfg.to_dict().items() if k != "visibility_stratified"} | {"visibility_rays": 64}
    assert not BakeConfig.from_dict(old).visibility_stratified       # baked before: one shared lattice
    with pytest.raises(ValueError):
        BakeConfig().with_updates(no_such_field=1)


def test_subtree_and_region_weights():
    parents = np.array([-1, 0, 1, 1, 0])          # 0 root; 1 spine; 2, 3 children of 1; 4 leg
    skin = np.eye(5)
    sub = subtree_weights(skin, parents, [1, 4])
    np.testing.assert_array_equal(sub, [[0, 0], [1, 0], [1, 0], [1, 0], [0, 1]])
    reg = region_weights(skin, parents, [1, 4])
    np.testing.assert_array_equal(reg, [[1, 0], [1, 0], [1, 0], [1, 0], [0, 1]])
    # joints 2 and 3 are neither the root nor refined: their weight is untracked
    blend = np.array([[0.5, 0.5, 0, 0, 0], [0, 0.25, 0.75, 0, 0], [0, 0, 0.5, 0.5, 0], [0, 0, 0, 0, 1.0]])
    np.testing.assert_allclose(untracked_skin_weight(blend, [1, 4]), [0.0, 0.75, 1.0, 0.0])
