"""Videos, HTML reports and contact sheets."""

from pathlib import Path

import numpy as np
import pytest

from uvatar.errors import InputError
from uvatar.render import contact_sheet, html_report, write_video


def frames(n=5, h=33, w=31):
    out = []
    for k in range(n):
        f = np.zeros((h, w, 3), np.float32)
        f[:, : (k + 1) * w // n] = [1.0, 0.5, 0.0]
        out.append(f)
    return out


def test_write_mp4_even_dims(tmp_path):
    import imageio.v3 as iio

    p = write_video(tmp_path / "v.mp4", frames(), fps=10)
    assert p == tmp_path / "v.mp4" and p.stat().st_size > 0
    back = iio.imread(p)
    assert back.shape[0] == 5 and back.shape[1:3] == (34, 32)
    assert not list(tmp_path.glob(".*"))  # no temp file left behind


def test_write_gif_and_bad_frames(tmp_path):
    p = write_video(tmp_path / "v.gif", frames(3, 10, 12), fps=5)
    assert p.suffix == ".gif" and p.stat().st_size > 0
    with pytest.raises(InputError):
        write_video(tmp_path / "x.mp4", [])
    with pytest.raises(InputError):
        write_video(tmp_path / "x.mp4", [np.zeros((4, 4, 3)), np.zeros((4, 6, 3))])


def test_html_report(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)  # relative media paths are relative to the working directory
    img = tmp_path / "media" / "a.png"
    img.parent.mkdir()
    img.write_bytes(b"")
    p = html_report(tmp_path / "report.html", "Eval <run>", [
        {"title": "Metrics", "text": "First paragraph.\n\nSecond & last.",
         "table": {"columns": ["frame", "psnr"], "rows": [["000001", 31.234567], ["000002", 29.5]]}},
        {"title": "Media", "images": [img, ("media/b.png", "caption b")], "videos": ["v.mp4"],
         "tables": [[{"name": "x", "value": 1}, {"name": "y", "value": 2.5}]]},
    ])
    text = p.read_text()
    assert "<title>Eval &lt;run&gt;</title>" in text and "<h2>Metrics</h2>" in text
    assert "<td>31.23</td>" in text and "Second &amp; last." in text
    assert 'src="media/a.png"' in text and 'src="media/b.png"' in text and "caption b" in text
    assert '<video src="v.mp4"' in text and "<th>value</th>" in text
    assert "http" not in text.replace("http-equiv", "")  # self-contained: nothing fetched


def test_html_report_links_relative_to_its_folder_from_any_working_directory(tmp_path, monkeypatch):
    """A report written as ``out/report.html`` from the folder above links ``out/capture/x.png`` as
    ``capture/x.png`` (the demo's bug: links relative to the working directory broke every image)."""
    out = tmp_path / "work" / "out"
    (out / "capture").mkdir(parents=True)
    monkeypatch.chdir(tmp_path / "work")
    html_report(Path("out") / "report.html", "r", [{"images": [Path("out") / "capture" / "x.png"],
                                                   "videos": [tmp_path / "work" / "out" / "a.mp4"]}])
    text = (out / "report.html").read_text()
    assert 'src="capture/x.png"' in text and 'src="a.mp4"' in text


def test_contact_sheet_layout_and_labels():
    imgs = [np.full((10, 12, 3), k / 4, np.float32) for k in range(5)]
    sheet = contact_sheet(imgs, cols=3, pad=2)
    assert sheet.shape == (2 * (10 + 2) + 2, 3 * (12 + 2) + 2, 3)
    np.testing.assert_allclose(sheet[2:12, 2 + 14 : 14 + 14], 0.25)  # image 1 in row 0, col 1
    labelled = contact_sheet(imgs, cols=3, pad=2, labels=["a", "bb", "c", "d", "e"], label_height=14)
    assert labelled.shape[0] == sheet.shape[0] + 2 * 14
    assert labelled[2:16, 2:14].min() < 0.5  # text drawn in the label strip
    gray = contact_sheet([np.zeros((4, 4), np.uint8), np.full((6, 2, 1), 255, np.uint8)])
    assert gray.shape[-1] == 3 and gray.max() == 1.0
    with pytest.raises(InputError):
        contact_sheet(imgs, labels=["a"])
    with pytest.raises(InputError):
        contact_sheet([])


def test_mp4_failure_falls_back_to_gif(tmp_path, monkeypatch):
    import imageio.v2 as imageio

    def broken(*a, **k):
        raise RuntimeError("no ffmpeg here")

    monkeypatch.setattr(imageio, "get_writer", broken)
    with pytest.warns(UserWarning, match="GIF"):
        p = write_video(tmp_path / "v.mp4", frames(2, 8, 8))
    assert p == tmp_path / "v.gif" and p.exists() and not (tmp_path / "v.mp4").exists()
