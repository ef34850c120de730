"""Speed paths of the bake keep their answers: float32 rays vs float64, visibility on a face subset
vs all faces, the symmetric SPD factorization vs a dense solve, one inpaint call for two maps."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
import trimesh

from uvatar.avh.bake.confidence import face_visibility, face_visibility_reference, vertex_visibility
from uvatar.avh.bake.inpaint import inpaint_telea
from uvatar.avh.bake.register import _factor_spd, fast_caster, uniform_laplacian_matrix
from uvatar.errors import InputError
from uvatar.geometry.raycast import RayCaster, RayCasterConfig, first_hit_reference


def sphere_and_plane():
    m = trimesh.creation.icosphere(subdivisions=2)
    v, f = np.asarray(m.vertices), np.asarray(m.faces)
    plane = np.array([[-3, -1.2, -3], [3, -1.2, -3], [3, -1.2, 3], [-3, -1.2, 3]], np.float64)
    return np.concatenate([v, plane]), np.concatenate([f, np.array([[0, 2, 1], [0, 3, 2]]) + len(v)])


def random_rays(n, seed=0):
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    return rng.uniform(-0.5, 0.5, (n, 3)), d * rng.uniform(0.5, 3.0, (n, 1))  # not unit


def test_float32_path_matches_float64_and_reference():
    v, f = sphere_and_plane()
    o, d = random_rays(3000)
    fast = RayCaster(v, f, RayCasterConfig(precision="float32"))
    slow = RayCaster(v, f, RayCasterConfig(precision="float64"))
    h32, h64 = fast.first_hit(o, d, max_distance=2.5), slow.first_hit(o, d, max_distance=2.5)
    ref = first_hit_reference(v, f, o, d, max_distance=2.5)
    assert h32.distance.dtype == np.float32 and h64.distance.dtype == np.float64
    np.testing.assert_array_equal(h32.hit, h64.hit)
    np.testing.assert_array_equal(h32.face, h64.face)
    np.testing.assert_array_equal(h32.hit, ref.hit)
    np.testing.assert_allclose(h32.distance[h32.hit], ref.distance[ref.hit], atol=2e-6)
    np.testing.assert_allclose(h32.points, ref.points, atol=2e-6)
    np.testing.assert_allclose(h32.bary, ref.bary, atol=2e-5)
    np.testing.assert_allclose(h32.bary.sum(1)[h32.hit], 1.0, atol=1e-6)
    np.testing.assert_array_equal(fast.any_hit(o, d, 2.5), slow.any_hit(o, d, 2.5))
    np.testing.assert_array_equal(fast.any_hit(o, d), slow.any_hit(o, d))
    np.testing.assert_array_equal(fast.count_hits(o, d), slow.count_hits(o, d))
    # refine recomputes in float64 on the float32 path too
    refined = RayCaster(v, f, RayCasterConfig(precision="float32", refine=True)).first_hit(o, d)
    np.testing.assert_allclose(refined.distance[refined.hit], first_hit_reference(v, f, o, d).distance[refined.hit],
                               atol=1e-6)


def test_float32_path_validates_like_float64():
    v, f = sphere_and_plane()
    rc = RayCaster(v, f, RayCasterConfig(precision="float32"))
    o, d = random_rays(10)
    for bad_o, bad_d, bad_m in [(o, np.zeros_like(d), np.inf), (o + np.nan, d, np.inf), (o, d, -1.0),
                                (o[:, :2], d[:, :2], np.inf), (o, d * np.inf, np.inf)]:
        with pytest.raises(InputError):
            rc.any_hit(bad_o, bad_d, bad_m)
    with pytest.raises(ValueError):
        RayCasterConfig(precision="float16")
    assert rc.any_hit(np.zeros((0, 3)), np.zeros((0, 3))).shape == (0,)


def test_visibility_subset_equals_full_and_reference():
    v, f = sphere_and_plane()
    full = face_visibility(v, f, n_rays=32)
    np.testing.assert_allclose(full, face_visibility_reference(v, f, n_rays=32))
    which = np.array([5, 0, 17, len(f) - 1, 40])
    np.testing.assert_allclose(face_visibility(v, f, n_rays=32, which=which, faces_per_batch=2), full[which])
    # the float32 caster gives the same occlusion answers as the float64 one
    f64 = face_visibility(v, f, RayCaster(v, f), n_rays=32)
    np.testing.assert_allclose(face_visibility(v, f, fast_caster(v, f), n_rays=32), f64)
    all_vertices = vertex_visibility(v, f, n_rays=32)
    needed = np.array([0, 3, 11, len(v) - 1])
    part = vertex_visibility(v, f, n_rays=32, needed=needed)
    np.testing.assert_allclose(part[needed], all_vertices[needed])
    rest = np.setdiff1d(np.arange(len(v)), needed)
    assert np.isnan(part[rest]).all()
    # each face's own lattice: the batched cast equals the per-face twin, and a face casts the same
    # rays whichever subset it is cast with
    strat = face_visibility(v, f, n_rays=12, stratified=True)
    np.testing.assert_allclose(strat, face_visibility_reference(v, f, n_rays=12, stratified=True))
    np.testing.assert_allclose(face_visibility(v, f, n_rays=12, which=which, faces_per_batch=2, stratified=True),
                               strat[which])
    part = vertex_visibility(v, f, n_rays=12, needed=needed, stratified=True)
    np.testing.assert_allclose(part[needed], vertex_visibility(v, f, n_rays=12, stratified=True)[needed])


def test_spd_factorization_solves_the_registration_system():
    m = trimesh.creation.icosphere(subdivisions=2)
    lap = uniform_laplacian_matrix(np.asarray(m.faces), len(m.vertices))
    w = (np.random.default_rng(0).random(len(m.vertices)) > 0.3).astype(float)
    a = (sp.diags(w + 1e-4) + 30.0 * (lap.T @ lap)).tocsc()
    b = np.random.default_rng(1).normal(size=(len(m.vertices), 3))
    np.testing.assert_allclose(_factor_spd(a).solve(b), np.linalg.solve(a.toarray(), b), atol=1e-9)


def test_inpaint_of_stacked_maps_equals_separate_calls():
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:48, 0:48] / 48.0
    tex = np.stack([np.sin(6 * xx), np.cos(5 * yy), xx * yy], -1).astype(np.float32)
    disp = (0.01 * rng.normal(size=(48, 48, 3))).astype(np.float32)
    fill = rng.random((48, 48)) > 0.7
    fill[:, :6] = True                                              # a region beyond the band
    both = inpaint_telea(np.concatenate([tex, disp], -1), fill, 3, band=2)
    np.testing.assert_array_equal(both[..., :3], inpaint_telea(tex, fill, 3, band=2))
    np.testing.assert_array_equal(both[..., 3:], inpaint_telea(disp, fill, 3, band=2))
