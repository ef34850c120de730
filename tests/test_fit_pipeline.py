"""``uvatar fit`` end to end on a small studio capture: the real detector, triangulation, the body fit."""

from __future__ import annotations

import shutil

import numpy as np
import pytest

from uvatar.errors import InputError

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _copy_without_fits(src, dst):
    shutil.copytree(src, dst)
    shutil.rmtree(dst / "fits")
    return dst


def _fitted_joints(root, frames):
    import torch

    from uvatar.body import load_body_model
    from uvatar.capture import Capture

    cap = Capture(root)
    body = load_body_model("anny")
    out = {}
    for frame in frames:
        fit = cap.load_fit(frame)
        with torch.no_grad():
            posed = body.pose(body.joint_rotvecs_from_fit(fit), Rh=fit.Rh, Th=fit.Th, shape=torch.as_tensor(fit.shapes))
        out[frame] = posed.joints[0].numpy()
    return out


def test_fit_refuses_to_replace_fits(fit_studio, tmp_path):
    from uvatar.fit.pipeline import FitConfig, fit_capture

    root = tmp_path / "cap"
    shutil.copytree(fit_studio[0], root)
    with pytest.raises(InputError, match="force=True replaces them"):
        fit_capture(root, FitConfig(source="images"), progress=False)


def test_fit_from_images_writes_fits_shape_and_provenance_and_resumes(fit_studio, tmp_path):
    from uvatar.capture import Capture
    from uvatar.fit.pipeline import FitConfig, fit_capture

    src, truth = fit_studio
    root = _copy_without_fits(src, tmp_path / "cap")
    summary = fit_capture(root, FitConfig(source="images", overlay_frames=1), progress=False)
    cap = Capture(root)
    assert summary["source"] == "images" and summary["frames"] == 2 and not summary["frames_without_detection"]
    assert all(cap.has_fit(f) for f in cap.frames)
    prov = cap.info["provenance"]["fit"]
    assert prov["detector"]["name"].startswith("mediapipe") and "keypoints3d" in prov["losses"]
    assert {"scan_distance", "photometric"} <= set(prov["losses"])   # the studio has scans: texture stage too
    assert len(cap.body_shapes) == len(cap.load_fit(cap.frames[0]).shapes) > 0  # one shape, in capture.json
    assert (root / "fitting" / "contact_sheet.png").is_file()
    assert summary["reprojection"]["fitted_body_px"]["median"] < 12  # at 256^2
    sem = truth["semantic"]
    body_joints = [sem[k] for k in ("pelvis", "l_hip", "r_hip", "l_knee", "r_knee", "l_ankle", "r_ankle",
                                    "l_shoulder", "r_shoulder", "l_elbow", "r_elbow", "l_wrist", "r_wrist")]
    fitted = _fitted_joints(root, cap.frames)
    err = [np.linalg.norm(fitted[f][body_joints] - truth[f][body_joints], axis=1).mean() for f in cap.frames]
    assert max(err) < 0.06, err  # metres, from 4 views of 256^2 pixels
    # a re-run with --force reuses the saved keypoints (nothing detected again)
    kp = sorted((root / "fitting" / "keypoints").glob("*.npz"))
    stamps = [p.stat().st_mtime_ns for p in kp]
    fit_capture(root, FitConfig(source="images", overlay_frames=0, force=True), progress=False)
    assert [p.stat().st_mtime_ns for p in kp] == stamps


def test_a_frame_without_a_person_is_reported_not_fatal(fit_studio, tmp_path):
    import imageio.v3 as iio

    from uvatar.capture import Capture
    from uvatar.fit.pipeline import FitConfig, fit_capture

    root = _copy_without_fits(fit_studio[0], tmp_path / "cap")
    cap = Capture(root)
    blank = cap.frames[1]
    for cam in cap.cameras():
        path = cap.image_path(cam, blank)
        iio.imwrite(path, np.zeros_like(iio.imread(path)))
    summary = fit_capture(root, FitConfig(source="images", overlay_frames=0, scan_distance=False), progress=False)
    assert list(summary["frames_without_detection"]) == [blank]
    assert Capture(root).has_fit(blank)  # fitted from its neighbour (temporal smoothness)
    # with every frame blank and no scans there is nothing to fit: one line, nothing written
    other = _copy_without_fits(fit_studio[0], tmp_path / "cap2")
    shutil.rmtree(other / "scans")
    for frame in Capture(other).frames:
        for cam in Capture(other).cameras():
            path = Capture(other).image_path(cam, frame)
            iio.imwrite(path, np.zeros_like(iio.imread(path)))
    with pytest.raises(InputError, match="none usable"):
        fit_capture(other, FitConfig(source="images", overlay_frames=0), progress=False)
    assert not (other / "fits").exists()


def test_cli_fit_existing_fits_is_one_line(fit_studio, tmp_path, capsys):
    from uvatar.cli.main import main

    root = tmp_path / "cap"
    shutil.copytree(fit_studio[0], root)
    assert main(["fit", str(root), "--from", "images", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--force" in err[0] and "force=True" not in err[0] and "fits" in err[0]


def test_views_that_disagree_are_named_left_out_and_fail_strict(fit_studio, tmp_path, capsys):
    """Camera 01's keypoints of frame 000001 moved 80 px (as a view that sees another person): fit
    names frame and camera, leaves the view out, fails under --strict, and ``capture check`` warns."""
    from dataclasses import replace

    from uvatar.capture import Capture
    from uvatar.cli.main import main
    from uvatar.fit.observe import load_observation, save_observation
    from uvatar.fit.triangulate import TriangulateConfig, triangulate

    root = _copy_without_fits(fit_studio[0], tmp_path / "cap")
    cap = Capture(root)
    frame = cap.frames[1]
    args = ["fit", str(root), "--from", "images", "--no-progress", "--no-scan-distance", "--overlay-frames", "0"]
    assert main(args) == 0 and "disagree" not in capsys.readouterr().err
    path = root / "fitting" / "keypoints" / f"{frame}.npz"
    obs = load_observation(path)
    cam = obs.cameras[1].name
    xy = obs.xy.copy()
    xy[1, :, 0] += 80.0
    tri = triangulate(xy, obs.conf, obs.cameras, TriangulateConfig())
    save_observation(path, replace(obs, xy=xy, points=tri.points.astype(np.float32), points_conf=tri.conf,
                                   reprojection_px=tri.reprojection_px.astype(np.float32)))
    assert main(args + ["--force", "--strict"]) == 1
    err = capsys.readouterr().err
    assert f"{frame} {cam}" in err and "--strict" in err
    assert main(["capture", "check", str(root), "--no-progress"]) == 0
    assert f"{frame} {cam}" in capsys.readouterr().out


def test_refine_cameras_turns_a_miscalibrated_view_back_and_masks_shape_the_fit(fit_studio, tmp_path, capsys):
    """Camera 01 turned by 1.2 deg (~7 px at 256^2): ``--refine-cameras`` turns it back (the calibration as
    it was kept in cameras/before_refine/, the saved keypoints through the new one) and ``--masks`` adds
    the silhouette term (the studio's true masks); without masks/ that flag is one line naming the
    command to run."""
    from uvatar.capture import Capture
    from uvatar.capture.cameras import read_cameras, write_cameras
    from uvatar.cli.main import main
    from uvatar.fit.calibration import rotated_camera
    from uvatar.fit.observe import load_observation
    from uvatar.fit.pipeline import FitConfig, fit_capture

    root = _copy_without_fits(fit_studio[0], tmp_path / "cap")
    shutil.rmtree(root / "fitting", ignore_errors=True)
    true = Capture(root).cameras()
    name = list(true)[1]
    wrong = dict(true, **{name: rotated_camera(true[name], [0.012, -0.016, 0.0])})
    write_cameras(root / "cameras", wrong)
    (root / "masks").rename(root / "true_masks")               # the studio's true person masks
    assert main(["fit", str(root), "--from", "images", "--masks", "--no-progress"]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--masks" in err[0] and "uvatar capture masks" in err[0], err
    (root / "true_masks").rename(root / "masks")

    def off_deg(cam):
        return float(np.degrees(np.arccos(np.clip((np.trace(cam.R.T @ true[name].R) - 1) / 2, -1, 1))))

    summary = fit_capture(root, FitConfig(source="images", refine_cameras=True, masks=True, overlay_frames=0,
                                          scan_distance=False), progress=False)
    refined = Capture(root).cameras()
    assert off_deg(refined[name]) < 0.5 * off_deg(wrong[name]), (off_deg(wrong[name]), off_deg(refined[name]))
    report = summary["cameras_refined"]
    assert report["reprojection_px_after"] < report["reprojection_px_before"]
    assert abs(report["leave_one_out_after"][name]["dx_px"]) < abs(report["leave_one_out_before"][name]["dx_px"])
    np.testing.assert_allclose(read_cameras(root / "cameras" / "before_refine")[name].R, wrong[name].R, atol=1e-9)
    saved = load_observation(root / "fitting" / "keypoints" / f"{Capture(root).frames[0]}.npz")
    np.testing.assert_allclose(saved.cameras[1].R, refined[name].R, atol=1e-9)
    assert "silhouette" in Capture(root).info["provenance"]["fit"]["losses"]


def test_mask_cameras_reads_only_the_named_cameras_masks(fit_studio, tmp_path, capsys):
    """``--mask-cameras`` keeps a held-out camera's masks out of the silhouette term; bad names and a
    missing ``--masks`` are one line in the command's flags."""
    from uvatar.capture import Capture
    from uvatar.cli.main import main
    from uvatar.fit.pipeline import FitConfig, _person_masks, mask_camera_names

    root = tmp_path / "cap"
    shutil.copytree(fit_studio[0], root)
    cap = Capture(root)
    cams = list(cap.cameras().values())
    keep = [c.name for c in cams[:-1]]
    config = FitConfig(masks=True, mask_cameras=" , ".join(keep))
    assert mask_camera_names(config) == keep
    frames = cap.frames[:2]
    every = _person_masks(cap, frames, cams, {})
    only = _person_masks(cap, frames, cams, {}, mask_camera_names(config))
    for row_all, row_only in zip(every, only, strict=True):
        assert row_only[-1] is None and row_all[-1] is not None          # the held-out camera: none
        for a, b in zip(row_all[:-1], row_only[:-1], strict=True):
            np.testing.assert_array_equal(a, b)                          # the others: unchanged

    for args, words in ((["--masks", "--mask-cameras", "nocam"], ("--mask-cameras", "nocam", cams[0].name)),
                        (["--mask-cameras", keep[0]], ("--mask-cameras", "--masks"))):
        assert main(["fit", str(root), "--from", "images", "--force", "--no-progress", *args]) == 1
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and all(w in err[0] for w in words) and "=True" not in err[0], err
