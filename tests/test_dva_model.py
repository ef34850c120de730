"""DVA primitives, texel-aligned features, decoders, losses and the assembled model (toy tube body)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from tests.fixtures.dva_capture import toy_cameras
from uvatar.dva.decoders import DecoderConfig, DvaDecoder, payload_to_slab, slab_to_payload
from uvatar.dva.features import (
    average_views,
    pose_feature_maps,
    texture_at_voxels,
    unwrap_views,
    view_feature_map,
    voxel_uv_grid,
)
from uvatar.dva.losses import DvaLoss, Vgg19Features, beta_prior, ssim_torch
from uvatar.dva.model import DvaModel, pixel_rays, preset
from uvatar.dva.primitives import (
    PrimitiveConfig,
    apply_correctives,
    articulated_frames,
    build_uv_grid,
)
from uvatar.dva.toy import ToyBody
from uvatar.errors import InputError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


@pytest.fixture(scope="module")
def body():
    return ToyBody()


def test_grid_snaps_and_scales(body):
    W = 32
    grid = build_uv_grid(body.template, PrimitiveConfig(grid=W, scale_factor=1.0))
    assert grid.raster.mask.all() and not grid.covered.all()  # UVs span [0.02, 0.98]: border snapped
    assert grid.covered[1:-1, 1:-1].all() and not grid.covered[0].any()
    # 16-gon tube: |dP/du| = perimeter / 0.96, |dP/dv| = height / 0.96 -> half the spacing W apart
    su = 16 * 2 * 0.15 * np.sin(np.pi / 16) / 0.96 / W / 2
    sv = 1.0 / 0.96 / W / 2
    np.testing.assert_allclose(grid.rest_scales[:, 1], sv, rtol=1e-4)
    np.testing.assert_allclose(grid.rest_scales[:, 0], su, rtol=1e-3)
    np.testing.assert_allclose(grid.rest_scales[:, 2], (su + sv) / 2, rtol=1e-3)


def test_articulated_frames_follow_the_surface(body):
    grid = build_uv_grid(body.template, PrimitiveConfig(grid=8))
    verts = body.pose(torch.zeros(2, 2, 3)).vertices
    pos, rot = articulated_frames(grid, body.template, verts)
    r = torch.linalg.norm(pos[0, :, [0, 2]], dim=-1)
    assert torch.all(r > 0.14) and torch.all(r <= 0.1501)  # on the tube (chords inside the circle)
    eye = torch.eye(3).expand_as(rot[0])
    assert torch.allclose(rot[0].transpose(1, 2) @ rot[0], eye, atol=1e-5)
    radial = pos[0].clone()
    radial[:, 1] = 0
    assert torch.all((rot[0, :, :, 2] * radial).sum(-1) > 0)  # normals point outward


def test_correctives(body):
    cfg = PrimitiveConfig(grid=4, max_translation=0.1, max_rotation=1.0)
    K = 16
    pos = torch.zeros(1, K, 3)
    rot = torch.eye(3).expand(1, K, 3, 3).clone()
    rest = torch.full((K, 3), 0.05)
    motion = torch.zeros(1, 9, 4, 4)
    p, r, s = apply_correctives(pos, rot, rest, motion, cfg, enabled=True)
    assert torch.equal(p, pos) and torch.allclose(r, rot) and torch.allclose(s[0], rest)
    motion[:, 0] = 100.0  # saturates tanh: +max_translation along local x
    motion[:, 6:9] = np.log(2.0)
    p, r, s = apply_correctives(pos, rot, rest, motion, cfg, enabled=True)
    assert torch.allclose(p[..., 0], torch.full((1, K), 0.1)) and torch.allclose(s, torch.full((1, K, 3), 0.1))
    p, _, s = apply_correctives(pos, rot, rest, motion, cfg, enabled=False)
    assert torch.equal(p, pos) and torch.allclose(s[0], rest)


def test_pose_features_are_masked_by_skinning(body):
    grid = build_uv_grid(body.template, PrimitiveConfig(grid=8))
    from uvatar.dva.features import texel_skin_weights

    w = torch.as_tensor(texel_skin_weights(grid.raster, body.template, (1,)))
    rv = torch.zeros(1, 2, 3)
    rv[0, 1] = torch.tensor([0.1, 0.2, 0.3])
    maps = pose_feature_maps(rv, w, (1,))
    assert maps.shape == (1, 3, 8, 8)
    # bottom rows (v small = image bottom) carry no weight of the bending joint; top rows carry all
    assert torch.all(maps[0, :, -1] == 0)
    assert torch.allclose(maps[0, :, 0], torch.tensor([0.1, 0.2, 0.3])[:, None].expand(3, 8))


def test_view_features_analytic(body):
    grid = build_uv_grid(body.template, PrimitiveConfig(grid=8))
    verts = body.pose(torch.zeros(1, 2, 3)).vertices
    far = torch.tensor([[0.0, 0.5, 1e4]])  # camera far along +Z: dot = normal_z
    f = view_feature_map(grid.raster, body.template, verts, far)[0, 0]
    assert f.shape == (8, 8)
    # texel column j has u = (j + 0.5) / 8 on facet floor((u - 0.02) / 0.96 * 16) of the 16-gon, whose
    # normal points at angle (facet + 0.5) * 2 pi / 16 from +Z: its z component is the cosine
    u = (np.arange(8) + 0.5) / 8
    facet = np.floor((u - 0.02) / 0.96 * 16)
    want = np.cos((facet + 0.5) * 2 * np.pi / 16)
    np.testing.assert_allclose(f.numpy(), np.broadcast_to(want, (8, 8)), atol=1e-3)


def test_unwrap_visibility_and_average(body):
    from uvatar.geometry import rasterize_uv

    raster = rasterize_uv(body.template.uvs, body.template.uv_faces, 32)
    cams = list(toy_cameras(2, 32).values())  # front (+Z) and back (-Z)
    imgs = [np.full((32, 32, 3), 0.25, np.float32), np.full((32, 32, 3), 0.75, np.float32)]
    verts = body.pose(torch.zeros(1, 2, 3)).vertices[0].numpy()
    tex, vis = unwrap_views(raster, body.template, verts, cams, imgs)
    assert vis.shape == (2, 32, 32) and not (vis[0] & vis[1]).any()  # a tube side is seen by one camera
    assert 0.3 < vis[0][raster.mask].mean() < 0.6
    np.testing.assert_allclose(tex[0][vis[0]], 0.25, atol=1e-6)
    avg = average_views(torch.as_tensor(tex)[None], torch.as_tensor(vis)[None])[0]
    seen = torch.as_tensor(vis[1])
    assert torch.allclose(avg[:3, seen], torch.tensor(0.75)) and torch.allclose(avg[3, seen], torch.tensor(0.5))


def test_occluded_texels_are_not_visible(body):
    from uvatar.dva.features import unwrap_view
    from uvatar.geometry import RayCaster

    cam = toy_cameras(1, 32)["cam00"]  # on +Z looking at the tube
    pts = np.array([[0.0, 0.5, 0.15], [0.0, 0.5, -0.15]])
    nrm = np.array([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])  # second faces the camera but sits behind the tube
    verts = body.pose(torch.zeros(1, 2, 3)).vertices[0].numpy()
    caster = RayCaster(verts, body.template.faces)
    _, vis = unwrap_view(pts, nrm, cam, np.zeros((32, 32, 3), np.float32), None, caster)
    assert vis.tolist() == [True, False]


def test_slab_payload_round_trip():
    x = torch.randn(2, 4 * 3, 3 * 4, 3 * 4)  # C=3, S=4, W=3
    p = slab_to_payload(x, 3, 4)
    assert p.shape == (2, 9, 3, 4, 4, 4)
    assert torch.equal(payload_to_slab(p, 3), x)
    # primitive k = wy * W + wx owns rows wy*S.., columns wx*S..; voxel (z, y, x) of channel c
    assert p[1, 1 * 3 + 2, 2, 3, 1, 0] == x[1, 2 * 4 + 3, 1 * 4 + 1, 2 * 4 + 0]


def test_decoder_shapes_and_ranges():
    dec = DvaDecoder(DecoderConfig(voxels=4, hidden=8, min_channels=4), grid=4, pose_channels=3,
                     image_channels=5)
    motion, rgb, density, own = dec(torch.randn(2, 3, 4, 4), torch.randn(2, 5, 4, 4), torch.randn(2, 1, 4, 4))
    assert torch.equal(own, rgb)  # no colour skip: the decoder's own colour is the payload's
    assert motion.shape == (2, 9, 4, 4) and torch.all(motion == 0)  # zero-initialised correctives
    assert rgb.shape == (2, 16, 3, 4, 4, 4) and density.shape == (2, 16, 1, 4, 4, 4)
    assert rgb.min() >= 0 and rgb.max() <= 1 and density.min() >= 0
    assert dec.opacity.head.bias.shape == (1, 8, 4, 4)  # untied: one bias per channel and texel
    with pytest.raises(ValueError):
        DvaDecoder(DecoderConfig(voxels=6), 4, 3, 5)


def test_voxel_uv_grid_follows_the_primitive_axes(body):
    """Each voxel column's UV lands, on the rest surface, where the marcher puts that voxel: the
    primitive's centre plus its local x (tangent) and y (bitangent) offsets. A grid flipped in y
    within each primitive would miss by about a primitive's size."""
    import torch.nn.functional as F

    from uvatar.geometry import rasterize_uv, texel_positions

    W, S, tpl = 12, 4, body.template
    cfg = PrimitiveConfig(grid=W)
    grid = build_uv_grid(tpl, cfg)
    verts = torch.as_tensor(np.asarray(tpl.vertices, np.float32))[None]
    pos, rot = articulated_frames(grid, tpl, verts)
    uv = torch.as_tensor(voxel_uv_grid(grid.raster, tpl, S, cfg.scale_factor))
    assert uv.shape == (W * S, W * S, 2)
    hi = rasterize_uv(tpl.uvs, tpl.uv_faces, 256)  # the surface point at any UV: a fine position map
    surf = torch.as_tensor(texel_positions(hi, tpl.faces, verts[0].numpy()), dtype=torch.float32)
    seen = torch.as_tensor(hi.mask, dtype=torch.float32)[..., None]
    tex = torch.cat([surf * seen, seen], -1).permute(2, 0, 1)[None]
    g = torch.stack([2 * uv[..., 0] - 1, 1 - 2 * uv[..., 1]], -1)[None]
    look = F.grid_sample(tex, g, align_corners=False)[0]
    inside = look[3] > 0.999
    at_uv = (look[:3] / look[3:].clamp(min=1e-6)).permute(1, 2, 0)  # (W*S, W*S, 3)
    local = torch.as_tensor((2 * np.arange(S) + 1.0) / S - 1.0, dtype=torch.float32)
    scales = torch.as_tensor(grid.rest_scales).reshape(W, 1, W, 1, 3)
    axes = rot[0].reshape(W, 1, W, 1, 3, 3)
    for flip, ok in ((1.0, True), (-1.0, False)):
        placed = (pos[0].reshape(W, 1, W, 1, 3) + axes[..., 0] * (local[None, None, None, :, None] * scales[..., :1])
                  + axes[..., 1] * (flip * local[None, :, None, None, None] * scales[..., 1:2]))
        miss = (placed.reshape(W * S, W * S, 3) - at_uv).norm(dim=-1)[inside]
        size = scales[..., :2].mean(-1).expand(W, S, W, S).reshape(W * S, W * S)[inside]
        assert inside.sum() > 0.5 * inside.numel()
        assert (float((miss / size).median()) < 0.1) == ok, (flip, float((miss / size).median()))


def test_texture_at_voxels_known_answer():
    """A texture whose colour is its own UV gives back the UV where it was seen (bilinear is exact on a
    linear ramp); unseen texels neither darken their seen neighbours nor count in the weight."""
    R = 16
    u = (torch.arange(R) + 0.5) / R
    tex = torch.zeros(1, 4, R, R)
    tex[0, 0] = u[None, :].expand(R, R)
    tex[0, 1] = (1 - u)[:, None].expand(R, R)  # row 0 is v = 1
    tex[0, 3, :, : R // 2] = 1.0 / 3.0  # seen by one of three views, left half only
    tex[0, :3, :, R // 2:] = 0.0  # the unseen half is black, as average_views leaves it
    uv = torch.tensor([[[0.2, 0.3], [0.45, 0.7], [0.5, 0.5], [0.9, 0.5]]])  # (1, 4, 2)
    colour, weight = texture_at_voxels(tex, uv)
    assert colour.shape == (1, 3, 1, 4) and weight.shape == (1, 1, 1, 4)
    assert torch.allclose(colour[0, :2, 0, :2].T, uv[0, :2], atol=1e-6)
    assert torch.allclose(weight[0, 0, 0], torch.tensor([1.0, 1.0, 0.5, 0.0]))
    assert float(colour[0, 0, 0, 2]) == pytest.approx((R // 2 - 0.5) / R, abs=1e-6)  # the seen neighbour's


def test_decoder_colour_skip_starts_at_the_photo():
    """With the decoder's own logits at zero, a texel a view saw takes the photo's colour at every
    depth, an unseen one the decoder's (0.5); the decoder's own colour is reported apart."""
    dec = DvaDecoder(DecoderConfig(voxels=2, hidden=4, min_channels=2, shadow=False), grid=2, pose_channels=1,
                     image_channels=1, colour_skip=True)
    torch.nn.init.zeros_(dec.appearance.tail.conv.weight)
    colour = torch.rand(1, 3, 4, 4) * 0.9 + 0.05
    weight = torch.zeros(1, 1, 4, 4)
    weight[..., :2] = 1.0
    _, rgb, _, own = dec(torch.randn(1, 1, 2, 2), torch.randn(1, 1, 2, 2), torch.randn(1, 1, 2, 2),
                         (colour, weight))
    slab = payload_to_slab(rgb, 2)  # (1, 3 * S, 4, 4), channel c * S + z
    for z in range(2):
        assert torch.allclose(slab[0, z::2][:, :, :2], colour[0, :, :, :2], atol=1e-6)
        assert torch.allclose(slab[0, z::2][:, :, 2:], torch.full((3, 4, 2), 0.5))
    assert torch.allclose(own, torch.full_like(own, 0.5))
    assert dec.skip_gain is not None and float(dec.skip_gain.detach()) == 1.0


def test_decoder_without_depth_colour_paints_columns():
    """depth_colour off: one colour (and shadow) per voxel column, the same at every depth, while the
    density still varies with depth; a run saved before the option keeps colour in every voxel."""
    from uvatar.dva.model import DvaConfig

    torch.manual_seed(0)
    dec = DvaDecoder(DecoderConfig(voxels=4, hidden=8, min_channels=4, depth_colour=False), grid=3,
                     pose_channels=2, image_channels=2, colour_skip=True)
    skip = (torch.rand(2, 3, 12, 12), torch.rand(2, 1, 12, 12))
    _, rgb, density, own = dec(torch.randn(2, 2, 3, 3), torch.randn(2, 2, 3, 3), torch.randn(2, 1, 3, 3), skip)
    assert rgb.shape == (2, 9, 3, 4, 4, 4) and dec.appearance.tail.conv.out_channels == 3
    assert torch.equal(rgb, rgb[:, :, :, :1].expand_as(rgb)) and torch.equal(own, own[:, :, :, :1].expand_as(own))
    assert not torch.equal(density, density[:, :, :, :1].expand_as(density))
    d = DvaConfig().to_dict()
    del d["decoder"]["depth_colour"]
    assert DvaConfig.from_dict(d).decoder.depth_colour


def test_losses():
    a = torch.rand(1, 3, 16, 16)
    assert float(ssim_torch(a, a)) == pytest.approx(1.0, abs=1e-5)
    assert float(ssim_torch(a, 1 - a)) < 0.5
    assert float(beta_prior(torch.tensor([0.0, 1.0]))) == pytest.approx(0.0, abs=1e-6)
    assert float(beta_prior(torch.tensor([0.5]))) > 1.0
    loss = DvaLoss()
    total, terms = loss(a, a, torch.ones(1, 16, 16), torch.ones(1, 16, 16), torch.full((1, 4, 3), 0.1),
                        torch.full((4, 3), 0.1))
    assert terms["rgb"] == 0 and terms["ssim"] == pytest.approx(0, abs=1e-5) and terms["mask"] == 0
    assert terms["volume"] == pytest.approx(1.0) and "perceptual" not in terms


def test_beta_prior_stays_out_of_the_persons_mask():
    """With the mask term on, the beta prior acts only outside the mask: its value is the prior of the
    outside pixels (as a mean over all pixels) and the person's pixels get no gradient from it, so it no
    longer pulls an emptied avatar's opacity toward 0 against the mask term. With the mask term off, or
    the option off (runs saved before it), it acts everywhere."""
    from uvatar.dva.losses import LossConfig
    from uvatar.dva.model import DvaConfig

    alpha = torch.full((1, 4, 4), 0.05, requires_grad=True)
    mask = torch.zeros(1, 4, 4)
    mask[:, :2] = 1.0                                        # the top half is the person
    rgb, scales, rest = torch.zeros(1, 3, 4, 4), torch.full((1, 2, 3), 0.1), torch.full((2, 3), 0.1)
    only_beta = {f: 0.0 for f in ("rgb", "perceptual", "ssim", "volume", "motion", "colour_tv")}
    _, terms = DvaLoss(LossConfig(**only_beta)).terms(rgb, rgb, alpha, mask, scales, rest)
    assert float(terms["beta"]) == pytest.approx(float(beta_prior(alpha.detach()[:, 2:])) / 2, rel=1e-6)
    total, _ = DvaLoss(LossConfig(**only_beta, mask=0.0)).terms(rgb, rgb, alpha, mask, scales, rest)
    grad_everywhere, = torch.autograd.grad(total, alpha)
    assert (grad_everywhere > 0).all()                       # toward 0 at alpha 0.05, everywhere
    inside_pull = torch.autograd.grad(beta_prior(alpha, 1.0 - mask), alpha)[0]
    assert (inside_pull[:, :2] == 0).all() and (inside_pull[:, 2:] > 0).all()
    legacy = DvaConfig.from_dict({"loss": {"rgb": 1.0}}).loss
    assert legacy.beta_outside_mask is False and LossConfig().beta_outside_mask is True
    # the diagnostics beside the terms (not in the total): the person's share of the crop, its opacity there
    total, terms = DvaLoss(LossConfig(**only_beta)).terms(rgb, rgb, alpha, mask, scales, rest)
    assert float(terms["mask_fraction"]) == pytest.approx(0.5) and float(terms["opacity_in_mask"]) == pytest.approx(0.05)
    assert float(total.detach()) == pytest.approx(0.01 * float(terms["beta"]) + 0.1 * float(terms["mask"]), rel=1e-6)


def test_vgg_weights_load_and_reject(tmp_path):
    vgg = Vgg19Features()
    torch.save({k: v for k, v in vgg.state_dict().items() if k.startswith("features.")}, tmp_path / "v.pth")
    loaded = Vgg19Features.from_file(tmp_path / "v.pth")
    feats = loaded(torch.rand(1, 3, 32, 32))
    assert [f.shape[1] for f in feats] == [64, 128, 256, 512, 512]
    torch.save({"features.0.weight": torch.zeros(1)}, tmp_path / "bad.pth")
    with pytest.raises(InputError):
        Vgg19Features.from_file(tmp_path / "bad.pth")
    (tmp_path / "junk.pth").write_text("not a checkpoint")
    with pytest.raises(InputError, match="junk.pth"):
        Vgg19Features.from_file(tmp_path / "junk.pth")


def test_model_forward_render_and_backward(body):
    cfg = preset("tiny")
    model = DvaModel(cfg, body.template, body.conditioning_joints)
    verts = body.pose(torch.zeros(1, 2, 3)).vertices
    R = model.image_raster.resolution
    out = model(verts, torch.zeros(1, 2, 3), torch.rand(1, 4, R, R), torch.tensor([[0.0, 0.5, 2.5]]))
    K, S = 64, cfg.decoder.voxels
    assert out.payload.shape == (1, K, 4, S, S, S) and out.positions.shape == (1, K, 3)
    cam = toy_cameras(1, 16)["cam00"]
    yy, xx = np.mgrid[:16, :16]
    pix = np.stack([xx.ravel(), yy.ravel()], 1)
    o, d = pixel_rays(cam, pix)
    rgb, alpha = model.render_rays(out, 0, o, d, torch.ones(3))
    assert alpha.reshape(16, 16)[8, 8] > 0.5 and alpha.reshape(16, 16)[0, 0] == 0  # tube centre vs corner
    rgb.mean().backward()
    assert model.decoder.appearance.tail.bias.grad.abs().sum() > 0


def test_image_encoder_centred_and_old_runs_keep_theirs():
    """The centred encoder sees 2 x - 1 and ends linear (its output can take either sign and is not
    squashed); a run saved before the option loads with the leaky last layer it was trained with."""
    from uvatar.dva.features import FeatureConfig, ImageEncoder
    from uvatar.dva.model import DvaConfig

    torch.manual_seed(0)
    enc = ImageEncoder(4, 8)
    old = ImageEncoder(4, 8, centred=False)
    old.load_state_dict(enc.state_dict())
    tex = torch.rand(2, 4, 32, 32)
    assert torch.allclose(enc(tex), enc.net[:-1](2 * tex - 1)) and torch.allclose(old(tex), old.net(tex))
    assert FeatureConfig().image_centred
    d = DvaConfig().to_dict()
    del d["features"]["image_centred"]
    assert not DvaConfig.from_dict(d).features.image_centred
    d["features"]["colour_skip"] = True
    assert DvaConfig.from_dict(d).features.colour_skip  # an option a run can be trained with (off by default)
    del d["features"]["colour_skip"]  # and a run from before the colour skip has none
    assert not DvaConfig.from_dict(d).features.colour_skip


def test_per_sample_primitives_share_one_unbind_backward():
    """A batch's per-sample primitives are views from one ``unbind`` (one backward node per tensor for
    every sample, no zero-filled batch-sized gradient per sample) with the gradients of indexing."""
    from uvatar.dva.model import DvaOutput

    torch.manual_seed(0)
    B, K, S = 3, 4, 2
    leaves = [torch.randn(*shape, dtype=torch.float64, requires_grad=True)
              for shape in ((B, K, 3), (B, K, 3, 3), (B, K, 3), (B, K, 4, S, S, S))]
    weights = [torch.randn_like(t) for t in leaves]

    def loss(parts_of):
        return sum((w[b] * p).sum() * (b + 1) for b in range(B)
                   for w, p in zip(weights, parts_of(b), strict=True))

    out = DvaOutput(*[t * 2 for t in leaves], motion=torch.zeros(B, 9, 2, 2), learned_rgb=torch.zeros(B, K, 3))
    prims = [out.primitives(b) for b in range(B)]
    assert {type(p.payload.grad_fn).__name__ for p in prims} == {"UnbindBackward0"}
    assert len({id(p.payload.grad_fn) for p in prims}) == 1   # one node for every sample
    got = torch.autograd.grad(loss(lambda b: (prims[b].positions, prims[b].rotations, prims[b].scales,
                                              prims[b].payload)), leaves)
    want = torch.autograd.grad(loss(lambda b: tuple(2 * t[b] for t in leaves)), leaves)
    for g, w in zip(got, want, strict=True):
        torch.testing.assert_close(g, w, rtol=0, atol=0)
