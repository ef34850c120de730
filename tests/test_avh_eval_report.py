"""The HTML report of ``uvatar eval avh`` from a metrics dict: every method's row with its figures, a
column no method has left out, regions, the near / far bins, images linked relative to the report."""

from __future__ import annotations

from uvatar.avh.eval_report import _method_table, eval_report


def _metrics(tmp_path):
    image = tmp_path / "im" / "000120.png"
    image.parent.mkdir()
    image.write_bytes(b"\x89PNG\r\n\x1a\n")
    row = {"psnr_db": 15.5, "ssim": 0.8, "psnr_db_inside_both": 30.25, "silhouette_iou": 0.95, "geometry_mm": 3.9,
           "texture_r2_own_bake": 0.05, "regions": {"face": {"psnr_db_inside_both": 25.5}}}
    return {"avatar": "A", "capture": "C", "frames": ["000120", "000121"], "split": "frames given", "cameras": 4,
            "pose_source": "refined", "avh": row, "others": {},
            "baselines": {"nearest_pose": dict(row, psnr_db_inside_both=30.5)},
            "upper_bound": {"own_bake": dict(row, psnr_db_inside_both=31.0)},
            "nearest_training_distance_deg": {"000120": 2.0, "000121": 4.0},
            "distance_bins": [{"bin": "near", "frames": ["000120"], "distance_deg_min": 2.0, "distance_deg_max": 2.0,
                               "avh_psnr_db_inside_both": 30.75, "nearest_pose_psnr_db_inside_both": 30.0}],
            "images": [str(image)], "protocol": "how it was scored"}


def test_method_table_rows_and_columns(tmp_path):
    table = _method_table(_metrics(tmp_path))
    assert [r[0] for r in table["rows"]] == ["avh", "nearest_pose", "own_bake (ceiling)"]
    assert "texture R² vs own bake" in table["columns"] and "texture R² vs truth" not in table["columns"]
    assert table["rows"][1][table["columns"].index("PSNR inside both masks (dB)")] == 30.5


def test_report_links_images_relative_to_itself(tmp_path):
    page = eval_report(_metrics(tmp_path), tmp_path / "out" / "eval.html").read_text()
    assert 'src="../im/000120.png"' in page and "how it was scored" in page
    assert "<td>30.75</td>" in page and "<th>face</th>" in page and "median 3.00 deg" in page
    assert "30.25" in page and "own_bake (ceiling)" in page
