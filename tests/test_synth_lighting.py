"""The studio light (:mod:`uvatar.capture.synth.lighting`): known answers on simple scenes (a lone
plane is unoccluded, an overhang darkens, a roof's shadow falls where the key light puts it),
determinism, and the switch that turns it off (the unlit capture, array for array)."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.capture.synth.lighting import (
    LightConfig,
    Occluder,
    ambient_occlusion,
    cone_directions,
    cosine_directions,
    light_visibility,
    shade_points,
)


def _grid(x0, x1, z0, z1, y, n, flip=False):
    """A square grid at height y over [x0, x1] x [z0, z1]: (vertices (n*n, 3), faces) facing +Y (or -Y)."""
    xs, zs = np.meshgrid(np.linspace(x0, x1, n), np.linspace(z0, z1, n), indexing="ij")
    v = np.stack([xs.ravel(), np.full(n * n, y), zs.ravel()], 1)
    i = np.arange(n * n).reshape(n, n)
    a, b, c, d = i[:-1, :-1].ravel(), i[1:, :-1].ravel(), i[1:, 1:].ravel(), i[:-1, 1:].ravel()
    f = np.concatenate([np.stack([a, d, c], 1), np.stack([a, c, b], 1)])
    return v, (f[:, ::-1] if flip else f)


def _scene(*parts):
    vs, fs, k = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + k)
        k += len(v)
    return Occluder.build(np.concatenate(vs), np.concatenate(fs))


def _floor_points(n=19, y=0.0):
    xs = np.linspace(-0.9, 0.9, n)
    return np.stack([xs, np.full(n, y), np.zeros(n)], 1)


CFG = LightConfig(ao_rays=64, ao_distance=1.0)


def test_ray_patterns():
    d = cosine_directions(256)
    np.testing.assert_allclose(np.linalg.norm(d, axis=1), 1.0, atol=1e-12)
    assert d[:, 2].min() > 0
    assert abs(d[:, 2].mean() - 2 / 3) < 0.01       # E[cos] under a cosine-weighted hemisphere
    c = cone_directions((0, 1, 1), 8, 5.0)
    cos = c @ (np.array([0, 1, 1]) / np.sqrt(2))
    assert np.all(cos <= 1 + 1e-12) and np.all(cos >= np.cos(np.radians(5.0)) - 1e-9)
    np.testing.assert_allclose(cone_directions((0, 2, 0), 3, 5.0 * 0)[0], [0, 1, 0])


def test_a_lone_plane_is_fully_open():
    occ = _scene(_grid(-1, 1, -1, 1, 0.0, 11))
    ao = ambient_occlusion(occ, occ.vertices, occ.normals, CFG)
    np.testing.assert_array_equal(ao, 1.0)
    np.testing.assert_allclose(occ.normals, [[0, 1, 0]] * len(occ.normals), atol=1e-12)
    vis = light_visibility(occ, occ.vertices, occ.normals, (0.3, 1.0, 0.2), CFG)
    np.testing.assert_array_equal(vis, 1.0)


def test_a_point_under_an_overhang_is_darker():
    floor = _grid(-1, 1, -1, 1, 0.0, 21)
    roof = _grid(-0.1, 0.5, -0.5, 0.5, 0.15, 5, flip=True)   # a slab over x in [-0.1, 0.5]
    occ = _scene(floor, roof)
    pts = np.array([[0.3, 0.0, 0.0], [0.05, 0.0, 0.0], [-0.3, 0.0, 0.0], [-0.8, 0.0, 0.0]])
    ao = ambient_occlusion(occ, pts, np.tile([0.0, 1.0, 0.0], (4, 1)), CFG)
    assert ao[0] < 0.3, "deep under the roof most of the sky is hidden"
    assert ao[0] < ao[1] < ao[2] <= ao[3], "AO rises toward the open floor"
    assert ao[3] > 0.97


def test_the_key_lights_shadow_falls_where_expected():
    """A roof at height h over x in [-0.1, 0.1] and a light at 45 degrees toward +X: the shadow on
    the floor is the roof shifted by -h in x, i.e. x in [-0.2, 0.0]."""
    h = 0.1
    occ = _scene(_grid(-1, 1, -1, 1, 0.0, 5), _grid(-0.1, 0.1, -0.6, 0.6, h, 3, flip=True))
    cfg = LightConfig(shadow_rays=1)
    x = np.array([-0.35, -0.25, -0.18, -0.1, -0.02, 0.03, 0.08, 0.15, 0.3])
    pts = np.stack([x, np.zeros_like(x), np.zeros_like(x)], 1)
    vis = light_visibility(occ, pts, np.tile([0.0, 1.0, 0.0], (len(x), 1)), (1.0, 1.0, 0.0), cfg)
    np.testing.assert_array_equal(vis, ((x < -0.2 + cfg.bias) | (x > 0.0 + cfg.bias)).astype(float))
    # a light straight above puts the shadow right under the roof
    vis_up = light_visibility(occ, pts, np.tile([0.0, 1.0, 0.0], (len(x), 1)), (0.0, 1.0, 0.0), cfg)
    np.testing.assert_array_equal(vis_up, (np.abs(x) > 0.1).astype(float))
    # soft shadows: a wide light gives partial visibility near the edge only
    soft = light_visibility(occ, pts, np.tile([0.0, 1.0, 0.0], (len(x), 1)), (1.0, 1.0, 0.0),
                            LightConfig(shadow_rays=16, light_radius_deg=8.0))
    assert soft[0] == 1 and soft[-1] == 1 and soft[3] == 0 and 0 < soft[4] < 1


def test_shading_terms_and_determinism():
    floor = _grid(-1, 1, -1, 1, 0.0, 21)
    roof = _grid(-0.1, 0.5, -0.5, 0.5, 0.15, 5, flip=True)
    cfg = LightConfig(ao_rays=32, key=(0, 1, 0), fill=(1, 1, 0))
    pts = _floor_points() + [0, 0.001, 0]             # 1 mm above the floor: snapped onto it
    dirs = np.tile([0.0, 1.0, 0.0], (len(pts), 1))
    a = shade_points(_scene(floor, roof), pts, dirs, cfg)
    b = shade_points(_scene(floor, roof), pts, dirs, cfg)
    for k in ("shading", "ao", "key", "fill"):
        np.testing.assert_array_equal(a[k], b[k])
    assert a["snapped"].all()
    open_ = np.abs(pts[:, 0]) > 0.75
    np.testing.assert_allclose(a["key"][open_], cfg.key_intensity)          # n . l = 1, unshadowed
    np.testing.assert_allclose(a["fill"][open_], cfg.fill_intensity / np.sqrt(2))
    np.testing.assert_allclose(a["shading"], cfg.ambient * a["ao"] + a["key"] + a["fill"])
    under = (pts[:, 0] > 0.0) & (pts[:, 0] < 0.4)
    assert np.all(a["key"][under] == 0) and np.all(a["shading"][under] < a["shading"][open_].min())


@pytest.fixture(scope="module")
def lit_and_unlit(tmp_path_factory):
    from uvatar.capture.synth.config import preset
    from uvatar.capture.synth.pipeline import synthesize

    out = {}
    for light in ("studio", "none"):
        root = tmp_path_factory.mktemp(f"light_{light}") / "cap"
        synthesize(root, preset("quick", frames=2, cameras=1, image_size=48, scan_texture=64, gt_texels=48,
                                seed=4, preview=False, light=light), progress=False)
        out[light] = root
    return out


def test_the_light_is_baked_into_scans_images_and_gt(lit_and_unlit):
    from uvatar.capture.meshio import read_mesh

    lit, unlit = lit_and_unlit["studio"], lit_and_unlit["none"]
    with np.load(lit / "gt" / "frames" / "000001.npz") as z, np.load(unlit / "gt" / "frames" / "000001.npz") as u:
        m = z["mask"]
        assert {"albedo", "crease", "shading", "ao"} <= set(z.files)
        assert not {"albedo", "crease", "shading", "ao"} & set(u.files), "unlit gt keeps its old layout"
        np.testing.assert_allclose(z["texture"][m], np.clip(z["albedo"] * (z["crease"] * z["shading"])[..., None],
                                                            0, 1)[m], atol=2e-6)
        # the unlit texture is albedo x creases, exactly the lit capture's parts without the light
        np.testing.assert_allclose(u["texture"][m], (z["albedo"] * z["crease"][..., None])[m], atol=2e-6)
        for k in ("surface", "offset", "mask", "pose"):
            np.testing.assert_array_equal(z[k], u[k])
        sh = z["shading"][m]
        assert 0.0 <= sh.min() and sh.max() <= 1.1 and np.percentile(sh, 90) - np.percentile(sh, 10) > 0.3
        assert 0 <= z["ao"][m].min() and z["ao"][m].max() <= 1 and np.median(z["ao"][m]) > 0.8
    a, b = read_mesh(lit / "scans" / "000001.obj"), read_mesh(unlit / "scans" / "000001.obj")
    np.testing.assert_array_equal(a.vertices, b.vertices)
    assert a.texture.mean() < b.texture.mean() - 0.02, "the light darkens the scan texture on average"
    import imageio.v3 as iio

    ia = iio.imread(lit / "images" / "00" / "000001.png")
    ib = iio.imread(unlit / "images" / "00" / "000001.png")
    assert ia.shape == ib.shape and not np.array_equal(ia, ib)
    np.testing.assert_array_equal(iio.imread(lit / "masks" / "00" / "000001.png"),
                                  iio.imread(unlit / "masks" / "00" / "000001.png"))


def test_the_same_pose_gives_the_same_shading_and_gt_renders_agree(lit_and_unlit):
    from uvatar.capture.synth.gtmaps import GtRenderer

    root = lit_and_unlit["studio"]
    g = GtRenderer(root, 48)
    a, b = g.render("000000"), GtRenderer(root, 48).render("000000")
    np.testing.assert_array_equal(a["texture"], b["texture"])
    with np.load(root / "gt" / "frames" / "000000.npz") as z:
        np.testing.assert_allclose(a["texture"][z["mask"]], z["texture"][z["mask"]], atol=1e-5)


def test_light_switch_is_checked_and_old_captures_read_as_unlit():
    from uvatar.capture.synth.config import SynthConfig
    from uvatar.capture.synth.gtmaps import config_from_dict

    with pytest.raises(ValueError, match="light"):
        SynthConfig(light="dim")
    old = SynthConfig().to_dict()
    old.pop("light")
    old.pop("lighting")
    assert config_from_dict(old).light == "none"
    assert config_from_dict(SynthConfig().to_dict()).light == "studio"
    with pytest.raises(ValueError, match="ao_rays"):
        LightConfig(ao_rays=0)
