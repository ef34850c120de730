"""Embree ray casting: exact distances on a box and a sphere, hit counting, parity with the numpy twin."""

import numpy as np
import pytest
import trimesh

from uvatar.errors import InputError
from uvatar.geometry.raycast import RayCaster, RayCasterConfig, count_hits_reference, first_hit_reference


def box():
    m = trimesh.creation.box(extents=(2.0, 2.0, 2.0))  # [-1, 1]^3
    return np.asarray(m.vertices), np.asarray(m.faces)


def sphere(subdiv=4):
    m = trimesh.creation.icosphere(subdivisions=subdiv)
    return np.asarray(m.vertices), np.asarray(m.faces)


def random_dirs(n, seed=0):
    d = np.random.default_rng(seed).normal(size=(n, 3))
    return d / np.linalg.norm(d, axis=1, keepdims=True)


def test_box_exact_distances_from_inside():
    v, f = box()
    rng = np.random.default_rng(1)
    o = rng.uniform(-0.9, 0.9, (2000, 3))
    d = random_dirs(2000, 2)
    hits = RayCaster(v, f).first_hit(o, d * 3.7)  # directions need not be unit
    expect = np.min((1.0 - o * np.sign(d)) / np.abs(d), axis=1)
    assert hits.hit.all()
    np.testing.assert_allclose(hits.distance, expect, atol=1e-5)
    np.testing.assert_allclose(hits.points, o + d * expect[:, None], atol=1e-5)
    # barycentrics reproduce the hit point on the reported face
    recon = (v[f[hits.face]] * hits.bary[:, :, None]).sum(1)
    np.testing.assert_allclose(recon, hits.points, atol=1e-5)
    np.testing.assert_allclose(hits.bary.sum(1), 1.0, atol=1e-12)


def test_box_from_outside_and_misses():
    v, f = box()
    o = np.array([[0.2, 0.3, -5.0], [3.0, 0.1, 0.2], [0.0, 5.0, 0.0], [0.0, 5.0, 0.0]])
    d = np.array([[0, 0, 1.0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]])
    h = RayCaster(v, f).first_hit(o, d)
    np.testing.assert_array_equal(h.hit, [True, True, False, True])
    np.testing.assert_allclose(h.distance, [4.0, 2.0, np.inf, 4.0], atol=1e-6)
    assert h.face[2] == -1 and np.all(h.points[2] == 0)


def test_sphere_distances_within_chord_error():
    v, f = sphere(4)
    tri = v[f]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    inradius = np.min(np.abs((n / np.linalg.norm(n, axis=1, keepdims=True) * tri[:, 0]).sum(1)))
    rc = RayCaster(v, f)
    d = random_dirs(3000, 3)
    inside = rc.first_hit(np.zeros_like(d), d)
    assert inside.hit.all()
    assert inside.distance.min() >= inradius - 1e-9 and inside.distance.max() <= 1.0 + 1e-9
    outside = rc.first_hit(-3 * d, d)  # rays from r = 3 straight at the centre
    assert outside.hit.all()
    assert outside.distance.min() >= 2.0 - 1e-9 and outside.distance.max() <= 3.0 - inradius + 1e-9


def test_max_distance_any_hit_and_min_distance():
    v, f = box()
    rc = RayCaster(v, f)
    o = np.zeros((4, 3))
    d = np.tile([1.0, 0, 0], (4, 1))
    maxd = np.array([0.5, 0.999, 1.001, np.inf])
    h = rc.first_hit(o, d, max_distance=maxd)
    np.testing.assert_array_equal(h.hit, [False, False, True, True])
    np.testing.assert_array_equal(rc.any_hit(o, d, maxd), h.hit)
    # from the surface point x = 1 inward, skipping the start surface
    h2 = rc.first_hit(np.array([[1.0, 0.2, 0.1]]), np.array([[-1.0, 0, 0]]), min_distance=1e-4)
    np.testing.assert_allclose(h2.distance, [2.0], atol=1e-6)


def test_count_hits_analytic():
    v1, f1 = sphere(3)
    v = np.concatenate([v1, v1 * 2.0])  # two nested spheres, radii 1 and 2
    f = np.concatenate([f1, f1 + len(v1)])
    rc = RayCaster(v, f)
    d = random_dirs(500, 4)
    np.testing.assert_array_equal(rc.count_hits(np.zeros_like(d), d), 2)
    np.testing.assert_array_equal(rc.count_hits(np.zeros_like(d), d, max_distance=1.5), 1)
    np.testing.assert_array_equal(rc.count_hits(-5 * d, d), 4)  # through the centre: 4 crossings
    np.testing.assert_array_equal(rc.count_hits(-5 * d, -d), 0)  # pointing away
    np.testing.assert_array_equal(rc.count_hits(-5 * d, d, min_distance=3.5), 3)


def test_parity_with_reference_on_random_rays():
    v, f = sphere(2)
    v = v * np.array([1.0, 1.3, 0.7]) + 0.05 * np.random.default_rng(5).normal(size=v.shape)
    rng = np.random.default_rng(6)
    o = rng.uniform(-1.2, 1.2, (600, 3))
    d = random_dirs(600, 7)
    rc = RayCaster(v, f, RayCasterConfig(refine=True))
    fast = rc.first_hit(o, d)
    ref = first_hit_reference(v, f, o, d)
    np.testing.assert_array_equal(fast.hit, ref.hit)
    assert fast.hit.sum() > 100
    np.testing.assert_allclose(fast.distance[fast.hit], ref.distance[ref.hit], atol=1e-9)
    np.testing.assert_array_equal(fast.face, ref.face)
    np.testing.assert_allclose(fast.bary, ref.bary, atol=1e-9)
    np.testing.assert_array_equal(rc.count_hits(o, d), count_hits_reference(v, f, o, d))
    unrefined = RayCaster(v, f, RayCasterConfig(refine=False, batch_size=97)).first_hit(o, d)
    np.testing.assert_allclose(unrefined.distance[fast.hit], fast.distance[fast.hit], atol=1e-5)


def test_bad_inputs():
    v, f = box()
    rc = RayCaster(v, f)
    with pytest.raises(InputError):
        rc.first_hit(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(InputError):
        rc.first_hit(np.zeros((2, 3)), np.ones((3, 3)))
    with pytest.raises(InputError):
        rc.first_hit(np.zeros((2, 2)), np.ones((2, 2)))
    with pytest.raises(InputError):
        rc.count_hits(np.zeros((1, 3)), np.ones((1, 3)), max_distance=-1)
    with pytest.raises(InputError):
        RayCaster(v, f + 100)
    with pytest.raises(InputError):
        RayCaster(v, np.zeros((0, 3), dtype=int))


def test_hit_rows_select_every_field():
    """``RayHits.rows``: the same rows of every field, for a slice and an index array."""
    from uvatar.geometry.raycast import RayHits

    n = 5
    hits = RayHits(np.arange(n) % 2 == 0, np.arange(n, dtype=float), np.arange(n) - 1,
                   np.arange(3 * n, dtype=float).reshape(n, 3), -np.arange(3 * n, dtype=float).reshape(n, 3))
    for index in (slice(1, 4), np.array([4, 0])):
        part = hits.rows(index)
        for name in ("hit", "distance", "face", "bary", "points"):
            assert np.array_equal(getattr(part, name), getattr(hits, name)[index])
