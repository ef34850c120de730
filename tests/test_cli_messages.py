"""What the terminal shows: library messages that name a parameter come out in the command's flags
(translated once, where main() catches UvatarError), Ray's start-up log and ffmpeg's banner stay off
the terminal, and a flag's help never shows a second, contradicting default."""

from __future__ import annotations

import re
import shutil

import pytest

from uvatar.cli.main import main

PARAMETER = re.compile(r"\b[a-z_]+=(True|False|None)\b")


def _error(capsys_or_fd) -> str:
    err = [line for line in capsys_or_fd.readouterr().err.splitlines() if line.startswith("uvatar: error:")]
    assert len(err) == 1, err
    return err[0]


@pytest.fixture(scope="module")
def captures(tmp_path_factory):
    """Toy inputs: a camera capture with fits, one without, a scan capture with its baked data."""
    from tests.fixtures.dva_capture import write_toy_capture
    from tests.fixtures.toy_capture import make_toy_capture
    from uvatar.body.toy import ToyTubeBody

    root = tmp_path_factory.mktemp("messages")
    write_toy_capture(root / "cams", frames=2, cameras=2, size=16)
    shutil.copytree(root / "cams", root / "no_fits")
    shutil.rmtree(root / "no_fits" / "fits")
    shutil.copytree(root / "cams" / "images", root / "no_calibration" / "images")
    make_toy_capture(root / "toy", ToyTubeBody(), num_frames=3, heldout=1, resolution=16, image_size=16)
    return root


@pytest.mark.parametrize("argv, flag_words", [
    (["fit", "{root}/cams"], "--force replaces them"),
    (["fit", "{root}/cams", "--from", "scans", "--force"],
     "--from scans needs textured scans in scans/ (a capture of images alone: --from images)"),
    (["capture", "masks", "{root}/no_fits"], "(or --no-fit to use the segmenter alone"),
    (["bake", "{root}/toy/capture", "{root}/bake_out", "--texels", "16"],
     "made with --texels 32 (this run: --texels 16); rerun with the same settings to resume it, or --overwrite"),
    (["train", "avh", "{root}/toy/baked", "{root}/run"], "--resume continues it"),
    (["train", "dva", "{root}/cams", "{root}/run"], "--resume continues it"),
    (["body", "info", "--model", "smpl"], "pass --model-dir or set UVATAR_SMPL_DIR"),
    (["capture", "import", "{root}/no_calibration", "{root}/imported"], "; give --calibration"),
    (["motion", "convert", "{root}/legless.bvh", "{root}/x.npz"], "give them in a joint map (--map,"),
    (["motion", "convert", "{root}/legless.bvh", "{root}/x.npz", "--body", "smpl"],
     "pass --model-dir or set UVATAR_SMPL_DIR"),
])
def test_library_messages_name_the_commands_flags(captures, capsys, monkeypatch, argv, flag_words):
    from uvatar.io_utils import write_json

    monkeypatch.delenv("UVATAR_SMPL_DIR", raising=False)
    write_json(captures / "bake_out" / "dataset.json", {"texels": 32})  # another bake's resolution
    write_json(captures / "bake_out" / "stage.json", {"stage": "bake", "config": {"texels": 32}, "complete": True})
    (captures / "run").mkdir(exist_ok=True)
    (captures / "run" / "checkpoint.pt").write_bytes(b"x")
    (captures / "legless.bvh").write_text("HIERARCHY\nROOT Hips\n{\n OFFSET 0 0 0\n CHANNELS 3 Xposition Yposition "
                                          "Zposition\n JOINT Spine\n {\n  OFFSET 0 1 0\n  CHANNELS 3 Zrotation Yrotation "
                                          "Xrotation\n  End Site\n  {\n   OFFSET 0 1 0\n  }\n }\n}\nMOTION\nFrames: 2\n"
                                          "Frame Time: 0.04\n0 0 0 0 0 0\n0 0 0 0 0 0\n")
    assert main([a.format(root=captures) for a in argv]) == 1
    err = _error(capsys)
    assert flag_words in err and not PARAMETER.search(err), err


def test_eval_names_its_baked_flag(trained_toy_avatar, tmp_path, capsys, monkeypatch):
    import uvatar.body

    body, cap, _ = trained_toy_avatar(tmp_path, num_frames=4)
    monkeypatch.setattr(uvatar.body, "load_body_model", lambda name, **kw: body)
    assert main(["eval", "avh", str(tmp_path / "avatar"), str(cap), "--baked", str(tmp_path / "nowhere")]) == 1
    err = _error(capsys)
    assert "pass --baked" in err and "baked_dir" not in err, err


def test_translation_spells_every_kind_of_flag():
    """store_true, --x/--no-x, a renamed generated flag, a valued flag, a parameter without a flag."""
    from uvatar.cli.flags import in_flag_terms
    from uvatar.cli.main import build_cli

    cli = build_cli()
    masks, bake = cli.commands["capture masks"], cli.commands["bake"]
    every = cli.commands.values()
    assert in_flag_terms("x: use_fit=True or use_fit=False", masks, "uvatar capture masks", every) == \
        "x: --fit or --no-fit"
    assert in_flag_terms("overwrite=True; texels=64; model_dir", bake, "uvatar bake", every) == \
        "--overwrite; --texels 64; model_dir (no flag of `uvatar bake` sets it)"
    assert in_flag_terms("frobnicate=True", bake, "uvatar bake", every) == \
        "frobnicate=True (no flag of `uvatar bake` sets frobnicate)"
    # paths and file names that look like parameters stay as they are
    assert in_flag_terms("in/cap_fits/fits: model_dir.json", masks, "uvatar capture masks", every) == \
        "in/cap_fits/fits: model_dir.json"


def test_unreachable_ray_address_is_one_line_without_rays_log(tmp_path, capfd):
    pytest.importorskip("ray")
    assert main(["synth", str(tmp_path / "s"), "--preset", "quick", "--executor", "ray", "--address", "127.0.0.1:1",
                 "--no-progress"]) == 1
    out = capfd.readouterr()
    err = [line for line in out.err.splitlines() if line.strip()]
    assert err[-1].startswith("uvatar: error: 127.0.0.1:1: no Ray cluster answers there"), err
    assert "--address none" in err[-1] and not any("gcs" in line.lower() or "rpc" in line for line in err), err


def test_unreadable_video_error_has_no_ffmpeg_banner(shared_data, tmp_path, capsys):
    (tmp_path / "rec" / "videos").mkdir(parents=True)
    shutil.copy(shared_data / "pose2sim_single" / "Calib.qca.txt", tmp_path / "rec")
    (tmp_path / "rec" / "videos" / "cam01.mp4").write_bytes(bytes(range(256)) * 20)
    assert main(["capture", "import", str(tmp_path / "rec"), str(tmp_path / "out")]) == 1
    err = _error(capsys)
    assert "cam01.mp4: cannot open video (" in err and "Invalid data" in err, err
    assert "ffmpeg version" not in err and "configuration" not in err and "@ 0x" not in err and len(err) < 300, err


def test_no_flag_help_shows_two_defaults():
    """A flag whose help states its own default gets no second one from argparse
    (capture import's "--calibration ... (default: found in SRC)" once showed "(default: None)")."""
    import argparse

    from uvatar.cli.main import build_cli

    cli = build_cli()
    for name, parser in cli.commands.items():
        formatter = parser._get_formatter()
        for action in parser._actions:
            if action.help in (None, argparse.SUPPRESS):
                continue
            text = formatter._expand_help(action)
            assert text.lower().count("(default") <= 1, (name, action.option_strings, text)
    help_text = cli.commands["capture import"].format_help()
    assert "found in SRC)" in help_text and "(default: None)" not in help_text
