"""Synthetic studio parts: appearance, clothing, scans, cameras, fits (anny template, CPU)."""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp

from uvatar.capture.synth import appearance as app
from uvatar.capture.synth import clothing as clo
from uvatar.capture.synth import surface as srf
from uvatar.capture.synth.bends import BENDS, smoothstep, value_noise
from uvatar.capture.synth.scans import build_topology, cut_scan, fine_mesh, pose_scan
from uvatar.geometry.uv_raster import fill_atlas_index


@pytest.fixture(scope="module")
def body():
    from uvatar.body import load_body_model

    return load_body_model("anny")


@pytest.fixture(scope="module")
def vertex_features(body):
    t = body.template
    W = sp.identity(t.num_vertices, format="csr")
    f = srf.features(W, t.vertices, srf.vertex_groups(body))
    L = srf.landmarks(body)
    return f, L, app.regions(f, L, app.AppearanceConfig())


def _nearest(f, point):
    return int(np.argmin(np.linalg.norm(f.p - np.asarray(point), axis=1)))


def test_value_noise_deterministic_smooth_and_bounded():
    p = np.random.default_rng(0).uniform(-1, 1, (500, 3))
    a, b = value_noise(p, 10.0), value_noise(p, 10.0)
    assert np.array_equal(a, b) and a.min() >= 0 and a.max() <= 1 and a.std() > 0.05
    assert np.abs(value_noise(p + 1e-4, 10.0) - a).max() < 0.01
    assert smoothstep(0, 1, np.array([-1, 0.5, 2])).tolist() == [0.0, 0.5, 1.0]


def test_regions_on_the_body(vertex_features):
    f, L, reg = vertex_features
    chest = _nearest(f, L["spine3"] + [0.0, -0.05, 0.15])
    thigh = _nearest(f, 0.5 * (L["l_hip"] + L["l_knee"]) + [0, 0, 0.08])
    hand = _nearest(f, L["l_wrist"] + [0.05, -0.03, 0.02])
    crown = int(np.argmax(f.p[:, 1]))
    sole = _nearest(f, L["r_ankle"] + [0, -0.06, 0.05])
    assert reg.shirt[chest] > 0.9 and reg.jeans[thigh] > 0.9 and reg.skin[hand] > 0.9
    assert reg.hair[crown] > 0.9 and reg.shoe[sole] > 0.9
    total = reg.shirt + reg.jeans + reg.belt + reg.shoe + reg.hair + reg.eye + reg.skin
    assert np.allclose(total[reg.skin > 0], 1.0, atol=1e-6) or total.max() <= 1.0 + 1e-6


def test_albedo_plaid_and_shading(vertex_features):
    f, L, reg = vertex_features
    rgb = app.albedo(f, L, reg=reg)
    assert rgb.shape == (len(f), 3) and rgb.dtype == np.float32 and rgb.min() >= 0 and rgb.max() <= 1
    shirt = rgb[reg.shirt > 0.99]
    assert shirt.std(0).max() > 0.08, "the plaid must vary"
    creases = app.crease_maps(f, L)
    assert creases.shape == (len(f), len(BENDS)) and creases.min() >= 0 and creases.max() <= 1
    assert np.array_equal(app.shade(rgb, creases, np.zeros(len(BENDS))), rgb)
    bends = np.zeros(len(BENDS))
    bends[BENDS.index("l_elbow")] = 1.0
    dark = app.shade(rgb, creases, bends)
    assert np.all(dark <= rgb + 1e-7)
    elbow = _nearest(f, L["l_elbow"] + [0.0, 0.0, 0.04])
    far = _nearest(f, L["r_knee"])
    assert dark[elbow].sum() < 0.8 * rgb[elbow].sum() and np.allclose(dark[far], rgb[far])


def test_clothing_offsets(vertex_features):
    f, L, reg = vertex_features
    cfg = clo.ClothingConfig()
    base = clo.base_offset(f, L, reg, cfg)
    assert np.median(base[reg.shirt > 0.99]) == pytest.approx(cfg.shirt, abs=0.002)
    assert np.median(base[reg.jeans > 0.99]) == pytest.approx(cfg.trousers, abs=0.002)
    assert np.all(base[reg.skin > 0.99] < 1e-3)
    folds = clo.fold_maps(f, L, reg, cfg)
    knee = np.linalg.norm(f.p - L["l_knee"], axis=1) < 0.08
    straight = clo.offset_amount(base, folds, np.zeros(len(BENDS)), cfg)
    bent = clo.offset_amount(base, folds, np.eye(len(BENDS))[BENDS.index("l_knee")], cfg)
    assert bent[knee].std() > 1.5 * straight[knee].std(), "folds must follow the knee bend"
    far = np.linalg.norm(f.p - L["l_knee"], axis=1) > 0.3
    assert np.allclose(bent[far], straight[far], atol=1e-4)
    assert bent.max() <= cfg.max_offset


def test_cut_scan_removes_the_requested_area():
    g = np.stack(np.meshgrid(np.linspace(0, 1, 21), np.linspace(0, 1, 21), indexing="ij"), -1).reshape(-1, 2)
    v = np.c_[g, np.zeros(len(g))]
    i = np.arange(20)[:, None] * 21 + np.arange(20)[None]
    i = i.ravel()
    faces = np.concatenate([np.c_[i, i + 21, i + 1], np.c_[i + 1, i + 21, i + 22]])
    keep = cut_scan(v, faces, np.array([1.0, 0.0, 0.0]), 0.5)
    assert len(keep) == len(faces) // 2
    assert v[faces[keep]].mean(1)[:, 0].max() < 0.5


def test_fill_atlas_index_bleeds_nearest():
    mask = np.zeros((4, 5), bool)
    mask[1, 1] = mask[2, 4] = True
    idx = fill_atlas_index(mask).reshape(4, 5)
    assert idx[1, 1] == 6 and idx[0, 0] == 6 and idx[3, 4] == 14 and idx[2, 4] == 14


def test_topology_origins_reproduce_the_clothed_rest_surface(body):
    from uvatar.geometry.frames import vertex_normals

    t = body.template
    fine = fine_mesh(t, levels=1)
    W = srf.bary_matrix(t.faces, fine.origin_face, fine.origin_bary, t.num_vertices)
    n = srf.posed_points(W, t.vertices, vertex_normals(t.vertices.astype(np.float64), t.faces))[1]
    offset = np.full(len(fine.vertices), 0.01)
    topo = build_topology(fine, offset, n, 6000, np.random.default_rng(0), 128)
    assert 5000 < len(topo.faces) <= 6000 and topo.faces.shape == topo.uv_faces.shape
    assert np.allclose(topo.origin_bary.sum(1), 1) and topo.origin_bary.min() >= -1e-9
    assert topo.uvs.min() >= 0 and topo.uvs.max() <= 1
    Wv = topo.vertex_matrix(t.faces, t.num_vertices)
    pts, nrm = srf.posed_points(Wv, t.vertices, vertex_normals(t.vertices.astype(np.float64), t.faces))
    rest = pose_scan(pts, nrm, np.full(len(pts), 0.01), 0.0, np.random.default_rng(0))
    assert np.abs(rest - topo.rest).max() < 1e-5
    other = build_topology(fine, offset, n, 5500, np.random.default_rng(1), 128)
    assert len(other.faces) != len(topo.faces)

    # atlas texels -> body points: sparse fast path vs the per-texel reference twin
    from uvatar.capture.synth.scans import atlas_texel_matrix, atlas_texel_points_reference
    from uvatar.geometry.uv_raster import rasterize_uv

    raster = rasterize_uv(topo.uvs, topo.uv_faces, 24)
    Wt, flat = atlas_texel_matrix(topo, raster, t.faces, t.num_vertices)
    assert len(flat) == raster.mask.sum() > 50
    ref = atlas_texel_points_reference(topo, raster, t.faces, t.vertices.astype(np.float64))
    assert np.allclose(Wt @ t.vertices.astype(np.float64), ref, atol=1e-9)


def test_studio_cameras_look_at_the_person():
    from uvatar.capture.synth.cameras import StudioConfig, studio_cameras

    cams = studio_cameras(8, 100, StudioConfig())
    assert [c.name for c in cams] == [f"{k:02d}" for k in range(8)]
    heights = np.array([c.center[1] for c in cams])
    assert (heights > 2.0).sum() == 2
    for c in cams:
        assert np.allclose(c.project(np.array(StudioConfig().target)), [49.5, 49.5], atol=1e-6)


def test_fit_tracks_is_checked():
    from uvatar.capture.synth.config import SynthConfig, preset

    assert preset("quick").fit_tracks == "body"
    assert preset("quick", fit_tracks="all").fit_tracks == "all"
    with pytest.raises(ValueError, match="fit_tracks"):
        SynthConfig(fit_tracks="fingers")


def test_noisy_fit():
    from uvatar.capture.synth.fits import noisy_fit

    rng = np.random.default_rng(0)
    pose = np.zeros((104, 3))
    pose[1:] = rng.normal(0, 0.3, (103, 3))
    exact = noisy_fit(pose, np.zeros(3), np.ones(3), np.full(6, 0.5), 0.0, rng)
    assert np.allclose(exact.poses, pose.reshape(-1)) and np.allclose(exact.Th, 1)
    noisy = noisy_fit(pose, np.zeros(3), np.ones(3), np.full(6, 0.5), 2.0, rng)
    from scipy.spatial.transform import Rotation

    err = (Rotation.from_rotvec(noisy.poses.reshape(-1, 3)[1:]) * Rotation.from_rotvec(pose[1:]).inv()).magnitude()
    assert np.degrees(np.median(err)) == pytest.approx(2.0 * 0.674, rel=0.3)
    assert np.all(noisy.poses[:3] == 0)
    # a body-only fit: untracked joints (here 50..103) in the rest pose, tracked ones as without
    body_only = noisy_fit(pose, np.zeros(3), np.ones(3), np.full(6, 0.5), 2.0, np.random.default_rng(5),
                          tracked=range(1, 50))
    every = noisy_fit(pose, np.zeros(3), np.ones(3), np.full(6, 0.5), 2.0, np.random.default_rng(5))
    assert np.all(body_only.poses.reshape(-1, 3)[50:] == 0)
    np.testing.assert_array_equal(body_only.poses.reshape(-1, 3)[:50], every.poses.reshape(-1, 3)[:50])
    np.testing.assert_array_equal(body_only.Rh, every.Rh)
