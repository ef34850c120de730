"""``uvatar capture check`` on the EasyMocap and ZJU-MoCap layouts: a clean folder passes, each
missing part is a warning (``--strict``: one line, exit 1), sizes are compared with the intrinsics."""

from __future__ import annotations

import numpy as np
import pytest
from test_dva_data import make_zju

from tests.fixtures.dva_capture import toy_cameras
from uvatar.capture import BodyFit, write_cameras, write_fit
from uvatar.cli.main import main
from uvatar.dva.check import check_layout
from uvatar.errors import InputError
from uvatar.io_utils import write_image


def make_easymocap(root, frames=("000000", "000001", "000002"), fits=True, masks=True):
    cams = toy_cameras(3, 8)
    write_cameras(root, cams)
    for f in frames:
        if fits:
            write_fit(root / "output-smpl-3d" / "smpl" / f"{f}.json", BodyFit(poses=np.zeros(72, np.float32)))
        for c in cams:
            write_image(root / "images" / c / f"{f}.jpg", np.full((8, 8, 3), 0.3, np.float32))
            if masks:
                write_image(root / "mask" / c / f"{f}.png", np.ones((8, 8), np.float32))
    return root


def check(root, capsys, *flags):
    code = main(["capture", "check", str(root), "--no-progress", *flags])
    out, err = capsys.readouterr()
    return code, out, err


def test_clean_easymocap_and_zju_pass(tmp_path, capsys):
    code, out, _ = check(make_easymocap(tmp_path / "em"), capsys, "--strict")
    assert code == 0 and "(easymocap layout): OK" in out and "warning" not in out
    s = check_layout(tmp_path / "em")
    assert s["frames"] == 3 and s["fits"] == 3 and s["masks"] == {"cam00": 3, "cam01": 3, "cam02": 3}
    code, out, _ = check(make_zju(tmp_path / "zju", n_cams=4, n_frames=2, size=16), capsys, "--strict", "--deep")
    assert code == 0 and "(zju-mocap layout): OK" in out  # 16 px images at ratio 0.5 = the 8 px cameras


def test_easymocap_without_masks_or_fits_warns(tmp_path, capsys):
    root = make_easymocap(tmp_path / "em", fits=False, masks=False)
    code, out, _ = check(root, capsys)
    assert code == 0 and "OK with 4 warnings" in out
    assert "warning: 3 of 3 frames have no fit" in out
    assert "warning: camera cam01: 3 of 3 images have no mask" in out
    code, _, err = check(root, capsys, "--strict")
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 1 and len(lines) == 1 and "strict check: 3 of 3 frames have no fit" in lines[0] and "(+3 more warnings)" in lines[0]


def test_easymocap_images_without_fits_camera_without_images_and_sizes(tmp_path):
    root = make_easymocap(tmp_path / "em")
    (root / "output-smpl-3d" / "smpl" / "000002.json").unlink()
    for p in (root / "images" / "cam02").iterdir():
        p.unlink()
    write_image(root / "mask" / "cam00" / "000000.png", np.ones((16, 16), np.float32))
    w = check_layout(root)["warnings"]
    assert "1 image frames have no fit (first 000002)" in w
    assert any(x.startswith("camera cam02 has no images") for x in w)
    assert any(x.startswith("camera cam00: masks are 16x16 but the intrinsics say 8x8") for x in w)


def test_zju_missing_masks_and_params(tmp_path):
    root = make_zju(tmp_path / "zju", n_cams=4, n_frames=3, size=16)
    (root / "new_params" / "2.npy").unlink()
    (root / "mask_cihp" / "Camera_B2" / "000001.png").unlink()
    w = check_layout(root)["warnings"]
    assert w == ["1 of 3 frames have no fit (`uvatar fit` makes them)",
                 f"camera 1: 1 of 3 images have no mask ({root / 'mask_cihp' / 'Camera_B2'})"]


def test_other_folders_are_refused(tmp_path, capsys):
    with pytest.raises(InputError, match="not a capture, EasyMocap or ZJU-MoCap folder"):
        check_layout(tmp_path)
    code, _, err = check(tmp_path, capsys)
    assert code == 1 and "capture.json is missing" in err
