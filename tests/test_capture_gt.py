"""gt/info.json: the one reader returns a GtInfo (normalized frame names, takes, texels), bad files
raise the project's InputError naming the file."""

from __future__ import annotations

import pytest

from uvatar.capture.gt import GtInfo, gt_info_path, read_gt_info, write_gt_info
from uvatar.errors import InputError


def test_read_gt_info_known_answer(tmp_path):
    write_gt_info(tmp_path, {"heldout_frames": [5, "000007"], "broken_frames": ["000002"],
                             "heldout_cameras": ["03"], "takes": {"walk": [0, 4]},
                             "config": {"gt_texels": 256}, "seed": 3})
    info = read_gt_info(tmp_path)
    assert info == GtInfo(path=gt_info_path(tmp_path), heldout_frames=("000005", "000007"),
                          broken_frames=("000002",), heldout_cameras=("03",), takes={"walk": (0, 4)},
                          texels=256, config={"gt_texels": 256}, raw=info.raw)
    assert info.raw["seed"] == 3
    write_gt_info(tmp_path, {"texel_resolution": 128, "texels": 64})
    assert read_gt_info(tmp_path).texels == 128 and read_gt_info(tmp_path).heldout_frames == ()


@pytest.mark.parametrize("record", [{"heldout_frames": "000001"}, {"broken_frames": [1.5]},
                                    {"takes": {"walk": [0]}}, {"takes": {"walk": ["a", "b"]}},
                                    {"texel_resolution": "big"}, {"heldout_cameras": "03"}])
def test_read_gt_info_bad_fields(tmp_path, record):
    write_gt_info(tmp_path, record)
    with pytest.raises(InputError, match="info.json"):
        read_gt_info(tmp_path)


def test_read_gt_info_missing_and_bad_json(tmp_path):
    assert read_gt_info(tmp_path, required=False) is None
    with pytest.raises(InputError, match="only synthetic captures"):
        read_gt_info(tmp_path)
    gt_info_path(tmp_path).parent.mkdir(parents=True)
    gt_info_path(tmp_path).write_text("{not json")
    with pytest.raises(InputError, match="info.json"):
        read_gt_info(tmp_path, required=False)
