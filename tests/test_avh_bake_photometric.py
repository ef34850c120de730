"""The bake's cross-frame colour term: stencil colours and slopes with known answers on a textured
plane, the reference median, and a twist that the surface distance cannot see but the colours do
(a round tube; scan = the tube pushed out by 1 cm, striped in the tube's own UV layout)."""

from __future__ import annotations

import numpy as np
import pytest
from test_avh_bake_helpers import offset_scan

from uvatar.avh.bake.config import PoseRefineConfig
from uvatar.avh.bake.photometric import PhotoTarget, reference_colours, surface_colours
from uvatar.avh.bake.refine import fit_colours, refine_fit, refine_vertices
from uvatar.avh.bake.register import ScanSurface
from uvatar.capture import BodyFit, TexturedMesh


def _ramp_plane(size: int = 64):
    """A 2 m square in z = 0 with u = (x + 1) / 2, v = (y + 1) / 2 and texture (u, v, 0.5) at texel centres."""
    vertices = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float64)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    uvs = (vertices[:, :2] + 1) / 2
    centres = (np.arange(size) + 0.5) / size
    u, v = np.meshgrid(centres, centres[::-1])          # row 0 is v = 1
    texture = np.stack([u, v, np.full_like(u, 0.5)], -1).astype(np.float32)
    return TexturedMesh(vertices, faces, uvs, faces, texture)


def test_stencil_colour_and_slope_on_a_linear_ramp():
    scan = _ramp_plane()
    surface = ScanSurface.build(scan.vertices, scan.faces)
    rng = np.random.default_rng(0)
    points = np.concatenate([rng.uniform(-0.8, 0.8, (50, 2)), rng.uniform(-0.01, 0.01, (50, 1))], 1)
    normals = np.tile([0.0, 0.0, 1.0], (50, 1))
    colour, gradient, ok = surface_colours(surface, scan, points, normals, 0.02, 0.05, 0.5)
    assert ok.all()
    np.testing.assert_allclose(colour[:, 0], (points[:, 0] + 1) / 2, atol=1e-5)   # the ramp, at the foot point
    np.testing.assert_allclose(colour[:, 1], (points[:, 1] + 1) / 2, atol=1e-5)
    expected = np.zeros((3, 3))
    expected[0, 0] = expected[1, 1] = 0.5                                         # d u / d x = 1/2 per metre
    np.testing.assert_allclose(gradient, np.broadcast_to(expected, gradient.shape), atol=1e-4)
    far = points + [0, 0, 0.2]                                                     # beyond max_distance
    assert not surface_colours(surface, scan, far, normals, 0.02, 0.05, 0.5)[2].any()
    facing_away = surface_colours(surface, scan, points, normals, 0.02, 0.05, 0.5)   # normals flipped below
    assert facing_away[2].all()
    assert not surface_colours(surface, scan, points, -normals, 0.02, 0.05, 0.9)[2].any()


def test_reference_is_the_median_where_enough_frames_saw_the_vertex():
    c = np.full((4, 3, 3), np.nan)
    c[:, 0] = [[0.1] * 3, [0.2] * 3, [0.9] * 3, [0.3] * 3]       # seen by all four: median 0.25
    c[:2, 1] = 0.5                                               # seen twice only
    reference, known = reference_colours(c, min_frames=3)
    assert known.tolist() == [True, False, False]
    np.testing.assert_allclose(reference[0], 0.25)


@pytest.fixture(scope="module")
def twisted():
    """A round tube (the toy body at 64 segments), twisted at its "chest" joint about its own axis:
    the turned surface is the same surface, only the stripes around it show the turn."""
    from uvatar.body.toy import ToyTubeBody

    model = ToyTubeBody(rings=33, segments=64)
    y, x = np.mgrid[0:256, 0:256] / 256
    stripes = np.stack([0.5 + 0.4 * np.sin(2 * np.pi * 6 * x), 0.5 + 0.2 * np.sin(2 * np.pi * 4 * y),
                        np.full_like(x, 0.5)], -1).astype(np.float32)
    truth = BodyFit(poses=np.zeros(model.num_joints * 3, np.float32), Rh=[0.0, 0.3, 0.0], Th=[0.0, 0.0, 0.0])
    scan = offset_scan(model, truth, texture=stripes)
    chest = model.joint_names.index("chest")
    pose = truth.poses.reshape(-1, 3).copy()
    pose[chest, 1] += np.radians(8.0)
    start = BodyFit(poses=pose.reshape(-1), Rh=truth.Rh, Th=truth.Th)
    return model, truth, start, scan, ScanSurface.build(scan.vertices, scan.faces)


def _surface_error_mm(model, fit, truth):
    """Median distance (mm) of the posed body's vertices from where the true pose puts them."""
    from uvatar.avh.bake.frame import shadow_vertices

    return float(np.median(np.linalg.norm(shadow_vertices(model, fit) - shadow_vertices(model, truth), axis=1)) * 1000)


def test_colour_term_turns_back_a_twist_the_surface_distance_cannot_see(twisted):
    model, truth, start, scan, surface = twisted
    config = PoseRefineConfig(iterations=10)
    reference = fit_colours(model, truth, surface, scan, config, 0.005)   # what the other frames agree on
    assert reference.shape == (len(refine_vertices(model, config)), 3)
    target = PhotoTarget(np.nan_to_num(reference), np.isfinite(reference).all(1), 0.005)
    geometric, _ = refine_fit(model, start, surface, config)
    photometric, stats = refine_fit(model, start, surface, config, photo=target, scan_mesh=scan)
    before, kept, after = (_surface_error_mm(model, f, truth) for f in (start, geometric, photometric))
    assert before > 5.0 and kept > 0.8 * before     # the surface distance does not see the turn
    assert after < 0.1 * before                     # the colours take it out
    assert stats["colour_residual"][-1] < 0.2 * stats["colour_residual"][0]
    with pytest.raises(ValueError, match="scan_mesh"):
        refine_fit(model, start, surface, config, photo=target)


@pytest.mark.slow
def test_bake_refines_frames_together_and_keeps_the_reference_for_later_frames(tmp_path):
    from test_avh_bake_helpers import make_capture

    from uvatar.avh.bake.config import BakeConfig
    from uvatar.avh.bake.pipeline import bake_capture
    from uvatar.avh.bake.refine_together import REFERENCE_FILE

    cap = make_capture(tmp_path / "cap", n_frames=5, broken=(), fit_noise_deg=1.0)
    cfg = BakeConfig().with_updates(texels=32, visibility_rays=8, pose_refine_iterations=2,
                                    pose_refine_photometric_radii=(0.004,))
    few = tmp_path / "few"
    bake_capture(cap, few, cfg, frames=["000000", "000001"], progress=False)
    assert not (few / REFERENCE_FILE).exists()               # two frames make no median
    out = tmp_path / "out"
    bake_capture(cap, out, cfg, frames=["000000", "000001", "000002", "000003"], progress=False)
    with np.load(out / REFERENCE_FILE) as z:
        assert z["frames"].tolist() == ["000000", "000001", "000002", "000003"]
        reference, poses = z["reference"].copy(), z["poses"].copy()
        assert z["known"].mean() > 0.5
    with np.load(out / "frames" / "000002.npz") as z:          # the bake stores what it baked
        np.testing.assert_array_equal(z["pose"], poses[2])
    bake_capture(cap, out, cfg, frames=["000004"], progress=False)
    with np.load(out / REFERENCE_FILE) as z:                  # the later frame joins, the median stays
        assert z["frames"].tolist()[-1] == "000004"
        np.testing.assert_array_equal(z["reference"], reference)
        np.testing.assert_array_equal(z["poses"][:4], poses)


def test_chromaticity_is_unchanged_by_shading_and_its_gradient_is_the_quotient_rule():
    """A white light's shading s scales r, g, b alike: the chromaticity c / sum(c) stays; its
    gradient, against central differences of a colour field linear in the position."""
    from uvatar.avh.bake.photometric import chromaticity

    rng = np.random.default_rng(3)
    colour = rng.uniform(0.05, 1.0, (5, 3))
    np.testing.assert_allclose(chromaticity(0.37 * colour), chromaticity(colour), rtol=1e-12)
    np.testing.assert_allclose(chromaticity(colour).sum(1), 1.0, rtol=1e-12)
    np.testing.assert_allclose(chromaticity(np.array([[0.2, 0.2, 0.6]])), [[0.2, 0.2, 0.6]])
    grad = rng.normal(size=(5, 3, 3)) * 0.1          # d colour_c / d x_d of colour(x) = colour + grad @ x
    _, g = chromaticity(colour, grad)
    h = 1e-6
    for d in range(3):
        step = np.zeros(3)
        step[d] = h
        up = chromaticity(colour + grad @ step)
        down = chromaticity(colour - grad @ step)
        np.testing.assert_allclose(g[:, :, d], (up - down) / (2 * h), rtol=1e-6, atol=1e-8)


def test_photometric_space_is_checked():
    from uvatar.avh.bake.config import PoseRefineConfig

    with pytest.raises(Exception, match="photometric_space"):
        PoseRefineConfig(photometric_space="lab")


def test_both_rays_in_one_launch_choose_as_the_two_casts():
    """The device path casts every point's +n and -n rays in one launch, each to the full distance; the
    reference casts the -n rays only as far as the +n ray's compatible hit. Between two layers (a shirt
    over skin), with normals tilted either way and some facing away: the same faces and barycentrics,
    and the -n ray does win for some points."""
    torch = pytest.importorskip("torch")
    pytest.importorskip("warp")
    from uvatar.avh.bake.photometric import _nearer_compatible_hit
    from uvatar.avh.bake.register import fast_caster

    plane = _ramp_plane()
    vertices = np.concatenate([plane.vertices, plane.vertices + [0.0, 0.0, 0.02]])
    faces = np.concatenate([plane.faces, plane.faces + 4])
    surface = ScanSurface.build(vertices, faces)
    surface.caster = fast_caster(surface.vertices, surface.faces, "cpu")
    rng = np.random.default_rng(3)
    p = torch.as_tensor(np.concatenate([rng.uniform(-0.8, 0.8, (400, 2)), rng.uniform(-0.03, 0.05, (400, 1))], 1))
    n = torch.as_tensor(rng.normal(0, 0.3, (400, 3)) + [0.0, 0.0, 1.0]) * torch.as_tensor(rng.choice([-1.0, 1.0], (400, 1)))
    n = n / n.norm(dim=1, keepdim=True)
    start = (torch.full((400,), float("inf"), dtype=torch.float64), torch.full((400,), -1, dtype=torch.int64),
             torch.zeros((400, 3), dtype=torch.float64))
    far = torch.full((800,), 0.051, dtype=torch.float64)
    one = _nearer_compatible_hit(surface, p, n, 0.05, 0.5, 1e-3, torch.where,
                                 lambda o, d, _: surface.caster.first_hit_torch(o, d, far), *start, cat=torch.cat)
    two = _nearer_compatible_hit(surface, p, n, 0.05, 0.5, 1e-3, torch.where,
                                 lambda o, d, best: surface.caster.first_hit_torch(o, d, best.clamp(max=0.051)), *start)
    assert torch.equal(one[0], two[0]) and torch.equal(one[1], two[1])
    assert 50 < int((one[0] >= 0).sum()) < 400
    # the -n ray won somewhere: its hit lies behind the point (against its normal)
    hit = one[0] >= 0
    below = ((surface.caster.first_hit_torch(p[hit], -n[hit], far[: int(hit.sum())]).face == one[0][hit])
             & (surface.caster.first_hit_torch(p[hit], n[hit], far[: int(hit.sum())]).face != one[0][hit]))
    assert int(below.sum()) > 10
