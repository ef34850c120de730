"""DVA data sources: a tiny fake ZJU-MoCap folder (Neural Body protocol), EasyMocap, uvatar captures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from uvatar.dva.data import (
    CaptureSource,
    EasyMocapSource,
    ZjuMocapSource,
    box_mask,
    open_source,
)
from uvatar.errors import InputError
from uvatar.io_utils import write_image

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def make_zju(root, n_cams=21, n_frames=5, size=16, start=0):
    """annots.npy + Camera_B<i>/<frame>.jpg + mask_cihp + new_params, T in millimetres."""
    Ks, Rs, Ts, Ds, ims = [], [], [], [], []
    for c in range(n_cams):
        Ks.append(np.array([[20.0, 0, 8], [0, 20.0, 8], [0, 0, 1]]))
        Rs.append(np.eye(3))
        Ts.append(np.array([[0.0], [0.0], [3000.0 + c]]))  # mm
        Ds.append(np.zeros((5, 1)))
    for f in range(n_frames):
        ims.append({"ims": [f"Camera_B{c + 1}/{f:06d}.jpg" for c in range(n_cams)]})
        for c in range(n_cams):
            img = np.full((size, size, 3), 0.5, np.float32)
            write_image(root / f"Camera_B{c + 1}/{f:06d}.jpg", img)
            m = np.zeros((size, size), np.float32)
            m[4:12, 4:12] = 1
            write_image(root / f"mask_cihp/Camera_B{c + 1}/{f:06d}.png", m)
        (root / "new_params").mkdir(parents=True, exist_ok=True)
        np.save(root / "new_params" / f"{f + start}.npy",
                {"poses": np.full((1, 72), 0.01 * f), "Rh": np.zeros((1, 3)), "Th": np.array([[0.0, 0.1 * f, 0]]),
                 "shapes": np.zeros((1, 10))}, allow_pickle=True)
    np.save(root / "annots.npy", {"cams": {"K": Ks, "R": Rs, "T": Ts, "D": Ds}, "ims": ims}, allow_pickle=True)
    return root


def test_zju_protocol(tmp_path):
    src = open_source(make_zju(tmp_path), num_train_frames=3, test_every=1)
    assert isinstance(src, ZjuMocapSource)
    assert src.train_cameras == ["0", "6", "12", "18"] and len(src.test_cameras) == 17
    assert src.train_frames == ["0", "1", "2"] and src.test_frames == ["3", "4"]
    cam = src.cameras["5"]
    np.testing.assert_allclose(cam.T, [0, 0, 3.005])  # millimetres -> metres
    np.testing.assert_allclose(cam.K[0, 0], 10.0)  # ratio 0.5
    assert (cam.width, cam.height) == (8, 8)
    img, mask = src.image("5", "4"), src.mask("5", "4")
    assert img.shape == (8, 8, 3) and mask.shape == (8, 8)
    assert mask[4, 4] == 1 and mask[0, 0] == 0
    assert img[0, 0].max() == 0 and img[4, 4].min() > 0.4  # background set to black
    fit = src.fit("4")
    assert fit.poses.shape == (72,) and fit.Th[1] == pytest.approx(0.4)
    assert "0, 6, 12, 18" in src.protocol and src.eval_box_mask


def test_zju_params_starting_at_one(tmp_path):
    src = ZjuMocapSource(make_zju(tmp_path, n_cams=4, n_frames=2, start=1))
    assert src.fit("0").Th[1] == pytest.approx(0.0) and src.fit("1").Th[1] == pytest.approx(0.1)
    assert src.train_cameras == ["0"]


def test_zju_errors(tmp_path):
    root = make_zju(tmp_path, n_cams=2, n_frames=1)
    src = ZjuMocapSource(root)
    with pytest.raises(InputError, match="5.npy"):
        src.fit("5")
    (root / "annots.npy").write_bytes(b"garbage")
    with pytest.raises(InputError, match="annots.npy"):
        ZjuMocapSource(root)


def test_box_mask_is_the_projected_box():
    from uvatar.render.cameras import look_at_camera

    cam = look_at_camera((0, 0, 3.0), (0, 0, 0), fov_deg=40, width=64, height=64)
    verts = np.array([[-0.2, -0.2, -0.2], [0.2, 0.2, 0.2]])
    m = box_mask(cam, verts, 64, 64, pad=0.0)
    assert m[32, 32] and not m[0, 0] and not m[32, 2]
    ys, xs = np.nonzero(m)
    f = cam.K[0, 0]
    half = f * 0.2 / 2.8  # the near face is the widest
    assert abs((xs.max() - xs.min() + 1) - 2 * half) <= 2.5


def test_easymocap_layout(tmp_path):
    from tests.fixtures.dva_capture import toy_cameras
    from uvatar.capture import BodyFit, write_cameras, write_fit

    cams = toy_cameras(4, 8)
    write_cameras(tmp_path, cams)
    for f in ("000000", "000001"):
        write_fit(tmp_path / "output-smpl-3d/smpl" / f"{f}.json", BodyFit(poses=np.zeros(72, np.float32)))
        for c in cams:
            write_image(tmp_path / "images" / c / f"{f}.jpg", np.full((8, 8, 3), 0.3, np.float32))
            write_image(tmp_path / "mask" / c / f"{f}.png", np.ones((8, 8), np.float32))
    src = open_source(tmp_path)
    assert isinstance(src, EasyMocapSource)
    assert src.frames == ["000000", "000001"] and src.test_cameras == ["cam03"]
    assert src.image("cam00", "000001").shape == (8, 8, 3) and src.mask("cam00", "000000").min() == 1
    assert src.fit("000000").poses.shape == (72,)


def test_capture_source_protocol(tmp_path):
    from tests.fixtures.dva_capture import write_toy_capture

    root = write_toy_capture(tmp_path / "cap", frames=3, cameras=4, size=8)
    src = open_source(root)
    assert isinstance(src, CaptureSource)
    assert src.test_cameras == ["cam03"] and src.test_frames == ["000002"]
    assert src.train_frames == ["000000", "000001"] and src.body_model == "toy"
    info = json.loads((root / "gt/info.json").read_text())
    info.pop("heldout_cameras")
    info["broken_frames"] = ["000001"]
    (root / "gt/info.json").write_text(json.dumps(info))
    src = CaptureSource(root)
    assert src.test_cameras == ["cam03"] and src.train_frames == ["000000"]  # every 4th camera held out


def test_open_source_rejects_other_folders(tmp_path):
    with pytest.raises(InputError, match="not a capture"):
        open_source(tmp_path)
