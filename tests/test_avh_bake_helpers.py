"""Hand-made inputs for the bake tests (no tests here): a tiny capture whose scans are the posed
anny body pushed out along its normals by a known offset, textured with a known image in the body's
own UV layout, so baked displacement and texture have analytic answers; plus gt/ like `uvatar synth`."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

OFFSET = 0.01  # metres, scan = body + OFFSET * vertex normal


def pattern_texture(size: int = 128) -> np.ndarray:
    """(size, size, 3) smooth colour pattern in [0, 1] (row 0 = v 1)."""
    y, x = np.mgrid[0:size, 0:size] / size
    return np.stack([0.2 + 0.6 * x, 0.2 + 0.6 * y, 0.5 + 0.3 * np.sin(6 * x) * np.cos(4 * y)], -1).astype(np.float32)


def body():
    from uvatar.body import load_body_model

    return load_body_model("anny")


def frame_pose(model, seed: int, amount: float = 0.25) -> np.ndarray:
    """(J*3,) small random local rotations on the conditioning joints."""
    rng = np.random.default_rng(seed)
    pose = np.zeros((model.num_joints, 3), np.float32)
    joints = list(model.conditioning_joints)
    pose[joints] = rng.normal(0.0, amount / 3, (len(joints), 3))
    return pose.reshape(-1)


def offset_scan(model, fit, offset: float = OFFSET, cut_above: float | None = None, texture=None):
    """TexturedMesh: the posed body + offset * normal, body UVs; optionally faces above a height cut."""
    from uvatar.avh.bake.frame import shadow_vertices
    from uvatar.capture import TexturedMesh
    from uvatar.geometry import vertex_normals

    tpl = model.template
    v = shadow_vertices(model, fit)
    scan_v = v + offset * vertex_normals(v, tpl.faces)
    faces, uv_faces = tpl.faces, tpl.uv_faces
    if cut_above is not None:
        keep = scan_v[faces].mean(1)[:, 1] < cut_above
        faces, uv_faces = faces[keep], uv_faces[keep]
    return TexturedMesh(scan_v, faces, tpl.uvs, uv_faces, pattern_texture() if texture is None else texture)


def noisy_refinement(model):
    """(surface, noisy fit, config) of a small refinement case: a scan of a known pose (Rh, Th), the fit
    to refine off by 0.03 rad a joint and a few cm, 4 iterations on 800 vertices."""
    from uvatar.avh.bake.config import PoseRefineConfig
    from uvatar.avh.bake.register import ScanSurface
    from uvatar.capture import BodyFit

    truth = BodyFit(poses=frame_pose(model, 0), Rh=[0.0, 0.4, 0.0], Th=[0.1, 0.0, -0.2])
    scan = offset_scan(model, truth)
    surface = ScanSurface.build(scan.vertices, scan.faces)
    noisy = BodyFit(poses=frame_pose(model, 0) + np.random.default_rng(1).normal(0, 0.03, 3 * model.num_joints)
                    .astype(np.float32), Rh=[0.0, 0.45, 0.02], Th=[0.11, 0.01, -0.2])
    return surface, noisy, PoseRefineConfig(iterations=4, max_vertices=800)


def refinements_either_way(monkeypatch, switch: str, atol_rad: float, atol_mm: float) -> None:
    """:func:`noisy_refinement` refined on a device (CPU tensors) with ``refine_device.<switch>`` off (the
    twin) and on: poses, Rh within ``atol_rad``, Th within ``atol_mm`` / 1000 m, the residuals within
    ``atol_mm``; and the fit did move."""
    from uvatar.avh.bake import refine_device
    from uvatar.avh.bake.refine import refine_fit

    model = body()
    surface, noisy, config = noisy_refinement(model)
    outs = {}
    for on in (False, True):
        monkeypatch.setattr(refine_device, switch, on)
        outs[on] = refine_fit(model, noisy, surface, config, device="cpu")
    (ref, ref_stats), (out, stats) = outs[False], outs[True]
    np.testing.assert_allclose(out.poses, ref.poses, atol=atol_rad, rtol=0)
    np.testing.assert_allclose(out.Rh, ref.Rh, atol=atol_rad, rtol=0)
    np.testing.assert_allclose(out.Th, ref.Th, atol=atol_mm / 1000, rtol=0)
    np.testing.assert_allclose(stats["residual_mm"], ref_stats["residual_mm"], atol=atol_mm, rtol=0)
    assert np.abs(np.asarray(ref.poses) - np.asarray(noisy.poses)).max() > 1e-3       # it did refine


def make_capture(root, n_frames: int = 3, broken=(1,), unreadable=(), heldout=(), gt_texels: int = 64,
                 offset: float = OFFSET, fit_noise_deg: float = 0.0) -> Path:
    """A capture folder with scans/, fits/, capture.json and gt/ (info.json + frames/*.npz).

    Scans and gt come from the true pose; the written fits add ``fit_noise_deg`` of per-joint noise.
    """
    from uvatar.avh.bake.frame import BodyLayout, shadow_vertices
    from uvatar.capture import BodyFit, write_capture_info, write_fit, write_mesh
    from uvatar.geometry import sample_texture, texel_uv
    from uvatar.io_utils import write_json, write_npz

    root = Path(root)
    model = body()
    frames = [f"{i:06d}" for i in range(n_frames)]
    layout = BodyLayout.from_template(model.template, gt_texels)
    tex = pattern_texture()
    for i, name in enumerate(frames):
        fit = BodyFit(poses=frame_pose(model, i), Rh=[0.0, 0.3 * i, 0.0], Th=[0.1 * i, 0.0, 0.0])
        noise = np.zeros((model.num_joints, 3), np.float32)
        if fit_noise_deg:
            joints = list(model.conditioning_joints)
            noise[joints] = np.random.default_rng(100 + i).normal(0, np.radians(fit_noise_deg), (len(joints), 3))
        write_fit(root / "fits" / f"{name}.json",
                  BodyFit(poses=fit.poses + noise.reshape(-1), Rh=fit.Rh, Th=fit.Th))
        if i in unreadable:
            (root / "scans").mkdir(parents=True, exist_ok=True)
            (root / "scans" / f"{name}.obj").write_text("this is not an obj file\nf 1 2 x\n")
            continue
        shadow = shadow_vertices(model, fit)
        cut = float(np.percentile(shadow[:, 1], 45)) if i in broken else None
        scan = offset_scan(model, fit, offset, cut)
        write_mesh(root / "scans" / f"{name}.obj", scan)
        from uvatar.geometry import vertex_normals

        surface = layout.to_map(layout.at_texels(shadow + offset * vertex_normals(shadow, model.template.faces)),
                                dtype=np.float32)
        gt_tex = sample_texture(tex, texel_uv(gt_texels).reshape(-1, 2)).reshape(gt_texels, gt_texels, 3)
        write_npz(root / "gt" / "frames" / f"{name}.npz", pose=fit.poses, surface=surface,
                  texture=np.where(layout.raster.mask[..., None], gt_tex, 0).astype(np.float32),
                  offset=np.zeros_like(surface), mask=layout.raster.mask)
    write_capture_info(root, frames, body_model="anny")
    write_json(root / "gt" / "info.json", {"broken_frames": [frames[i] for i in broken],
                                           "heldout_frames": [frames[i] for i in heldout],
                                           "texels": gt_texels})
    return root


def test_heldout_frames_names_int_entries_and_is_empty_without_ground_truth(tmp_path):
    from uvatar.avh.bake.pipeline import heldout_frames
    from uvatar.capture import frame_name
    from uvatar.io_utils import write_json

    assert frame_name(5) == "000005" and frame_name("take_a_0003") == "take_a_0003"
    assert heldout_frames(tmp_path) == []                      # a real capture: no gt/
    (tmp_path / "gt").mkdir()
    (tmp_path / "gt" / "info.json").write_text("{not json")
    assert heldout_frames(tmp_path) == []                      # unreadable: no held-out frames
    write_json(tmp_path / "gt" / "info.json", {"heldout_frames": [7, "000009"]})
    assert heldout_frames(tmp_path) == ["000007", "000009"]


def _baked_stub(r: int = 16):
    from types import SimpleNamespace

    rng = np.random.default_rng(0)
    baked = SimpleNamespace(texture=rng.random((r, r, 3)).astype(np.float32),
                            displacement=rng.normal(0, 0.01, (r, r, 3)).astype(np.float32),
                            kappa=rng.random((r, r)).astype(np.float32), w=rng.random((r, r)).astype(np.float32),
                            valid=np.ones((r, r), bool), matched=rng.random((r, r)) > 0.3,
                            stats={"kappa_mean": 0.6, "matched_fraction": 0.7})
    fit = SimpleNamespace(poses=np.zeros(9, np.float32), Rh=np.zeros(3), Th=np.zeros(3), shapes=np.zeros(2),
                          scale=1.0)
    return baked, fit


def test_a_baked_frame_lands_after_its_preview_and_not_without_it(tmp_path, monkeypatch):
    """The preview is drawn on a thread while the maps compress, and is on disk before the frame (a frame
    on disk always has its preview); a preview that fails to write leaves no frame. The frame reads back
    (float16 texture, float32 displacement)."""
    from uvatar.avh.bake import dataset
    from uvatar.avh.bake.dataset import frame_path, load_baked_frame, preview_path, write_baked_frame

    baked, fit = _baked_stub()
    real = dataset.write_bytes
    seen = []

    def checked(path, data, suffix=None):
        seen.append(preview_path(tmp_path, "000003").is_file())
        real(path, data, suffix)

    monkeypatch.setattr(dataset, "write_bytes", checked)
    path = write_baked_frame(tmp_path, "000003", baked, fit)
    assert seen == [True] and path == frame_path(tmp_path, "000003")
    z = load_baked_frame(path)
    np.testing.assert_array_equal(z["displacement"], baked.displacement)
    np.testing.assert_allclose(z["texture"], baked.texture, atol=5e-4)

    def broken(*a, **k):
        raise OSError(28, "No space left on device", str(preview_path(tmp_path, "000004")))

    monkeypatch.setattr(dataset, "write_image", broken)
    with pytest.raises(OSError, match="No space"):
        write_baked_frame(tmp_path, "000004", baked, fit)
    assert not frame_path(tmp_path, "000004").exists()
