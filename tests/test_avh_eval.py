"""AVH evaluation on a toy capture with an exact bake: baselines, geometry error, metrics JSON."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from tests.fixtures.toy_capture import make_toy_capture
from uvatar.avh.data import load_frame
from uvatar.avh.eval import Baselines, EvalConfig, encoded_conditioning, evaluate_avatar
from uvatar.avh.eval_metrics import image_metrics, surface_error_mm
from uvatar.avh.export import export_avatar
from uvatar.avh.model import AvhConfig
from uvatar.avh.runtime import AvatarRuntime
from uvatar.avh.train import TrainConfig, train_avh
from uvatar.body.toy import ToyTubeBody
from uvatar.errors import InputError


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("eval")
    body = ToyTubeBody()
    cap, baked = make_toy_capture(root, body, num_frames=6, heldout=2, resolution=32)
    train_avh(baked, root / "run", AvhConfig(4, 32, resolution=32),
              TrainConfig(epochs=1, progress=False, tensorboard=False), body=body)
    export_avatar(root / "run", root / "avatar", body=body)
    return root, body, cap, baked


def test_encoded_conditioning_matches_model_encoding():
    import torch

    from uvatar.avh.model import encode_pose, select_conditioning_angles

    poses = np.random.default_rng(0).normal(size=(3, 18)).astype(np.float32)
    ref = encode_pose(select_conditioning_angles(torch.from_numpy(poses), [1, 3])).numpy()
    assert np.allclose(encoded_conditioning(poses, [1, 3]), ref, atol=1e-6)


def test_nearest_pose_returns_the_training_frame_itself(setup):
    root, body, _, baked = setup
    names = ["000000", "000001", "000002"]
    base = Baselines(baked, names, 32, body.conditioning_joints)
    frame = load_frame(baked / "frames" / "000001.npz")
    i, tex, disp = base.nearest(frame["pose"])
    assert base.frames.names[i] == "000001"
    valid = frame["valid"]
    assert np.array_equal(tex, frame["texture"]) and np.array_equal(disp[valid], frame["displacement"][valid])
    assert np.all(disp[~valid] == 0)
    assert base.mean_texture.shape == (32, 32, 3)


def test_surface_error_is_zero_with_the_true_displacement(setup):
    root, body, cap, baked = setup
    rt = AvatarRuntime(root / "avatar", body=body)
    frame = load_frame(baked / "frames" / "000002.npz")
    base = rt.posed_vertices(frame["pose"][None], frame["Rh"][None], frame["Th"][None])[0]
    with np.load(cap / "gt" / "frames" / "000002.npz") as z:
        surface, mask = z["surface"], z["mask"]
    keep = mask & ~rt.fingers_toes_mask()
    # the avatar learns rest-frame maps: unpose the baked body-frame map, let the eval re-pose it
    from uvatar.avh.displacement_frame import maps_body_to_rest
    from uvatar.geometry import rasterize_uv

    assert rt.displacement_frame == "rest"
    raster = rasterize_uv(body.template.uvs, body.template.uv_faces, 32)
    rest = maps_body_to_rest(body, raster, body.template.faces, frame["displacement"][None], frame["pose"][None])[0]
    rotations = rt.skinning_rotations(frame["pose"][None])[0]
    err = surface_error_mm(rt, base, rest, frame["Rh"], surface, keep, rotations)
    assert len(err) > 100 and err.max() < 1e-3
    err0 = surface_error_mm(rt, base, None, frame["Rh"], surface, keep)
    with np.load(cap / "gt" / "frames" / "000002.npz") as z:
        offset = np.linalg.norm(z["offset"], axis=-1)
    m = keep & rasterize_uv(body.template.uvs, body.template.uv_faces, 32).mask
    assert np.allclose(np.sort(err0), np.sort(offset[m] * 1000), atol=1e-2)


def test_image_metrics_union_mask():
    a = np.ones((8, 8, 3), np.float32)
    b = a.copy()
    b[:2] = 0.5
    ma = np.zeros((8, 8), bool)
    mb = np.zeros((8, 8), bool)
    ma[:2] = True  # union = top 2 rows; all of them differ by 0.5 -> MSE 0.25 -> 6.02 dB
    m = image_metrics(a, ma, b, mb)
    assert m["psnr_db"] == pytest.approx(10 * np.log10(4), rel=1e-6)
    assert np.isnan(image_metrics(a, mb, b, mb)["psnr_db"])


def test_image_metrics_split_appearance_and_shape():
    """inside-both PSNR sees only colour where both masks cover; IoU only the masks (known answers)."""
    gt = np.full((8, 8, 3), 0.5, np.float32)
    pred = gt.copy()
    pred[2:4] += 0.1                     # colour error 0.1 on rows 2-3 -> MSE over rows 2-5 = 0.005
    gm = np.zeros((8, 8), bool)
    pm = np.zeros((8, 8), bool)
    gm[2:6], pm[2:7] = True, True        # prediction covers one extra row: IoU 4/5
    pred[6] = 1.0                        # that row is white background in gt: counts in the union only
    m = image_metrics(pred, pm, gt, gm)
    assert m["silhouette_iou"] == pytest.approx(0.8)
    assert m["psnr_db_inside_both"] == pytest.approx(10 * np.log10(1 / 0.005), rel=1e-4)
    assert m["psnr_db"] < m["psnr_db_inside_both"]
    assert np.isnan(image_metrics(pred, np.zeros_like(pm), gt, np.zeros_like(gm))["silhouette_iou"])


def test_evaluate_avatar_reports_all_methods(setup, tmp_path):
    root, body, cap, _ = setup
    m = evaluate_avatar(root / "avatar", cap, EvalConfig(progress=False, image_size=48, pose_source="fit"),
                        image_dir=tmp_path, body=body)
    assert m["frames"] == ["000004", "000005"] and m["split"] == "heldout" and "union" in m["protocol"]
    methods = {"avh": m["avh"], "mean_texture": m["baselines"]["mean_texture"],
               "nearest_pose": m["baselines"]["nearest_pose"]}
    for name, res in methods.items():  # the summary is the mean of the per-frame scores
        assert res["psnr_db"] == pytest.approx(np.mean([e[f"{name}_psnr_db"] for e in m["per_frame"]]))
    # known answer: the toy's fits are exact, so the mean texture (no displacement) lies on the posed body
    # and its surface error is exactly the true clothing offset
    offsets = []
    for f in m["frames"]:
        with np.load(cap / "gt" / "frames" / f"{f}.npz") as z:
            offsets.append(np.linalg.norm(z["offset"][z["mask"]], axis=-1) * 1000.0)
    assert m["baselines"]["mean_texture"]["geometry_mm"] == pytest.approx(np.concatenate(offsets).mean(), rel=1e-5)
    assert m["baselines"]["nearest_pose"]["psnr_db"] > 15  # exact maps of a similar pose
    assert len(m["images"]) == 2 and all((tmp_path / f"{f}.png").is_file() for f in m["frames"])
    json.dumps(m)  # JSON-serializable


def test_evaluate_needs_baked_data(setup, tmp_path):
    root, body, cap, _ = setup
    with pytest.raises(InputError, match="pass baked_dir"):
        evaluate_avatar(root / "avatar", cap, EvalConfig(progress=False), baked_dir=tmp_path, body=body)


def test_cli_eval(setup, tmp_path, monkeypatch, capsys):
    import uvatar.body
    from uvatar.cli.main import main

    root, body, cap, _ = setup
    monkeypatch.setattr(uvatar.body, "load_body_model", lambda name, **kw: body)
    out = tmp_path / "m.json"
    assert main(["eval", str(root / "avatar"), str(cap), "--json", str(out), "--image-size", "32",
                 "--frames", "1", "--cameras", "1"]) == 0
    m = json.loads(out.read_text())
    assert m["frames"] == ["000004"] and m["cameras"] == 1
    assert "nearest_pose" in capsys.readouterr().out
    assert main(["eval", str(root / "avatar"), str(tmp_path / "nope")]) == 1


def test_image_metrics_reports_both_protocols():
    a = np.ones((8, 8, 3), np.float32)
    b = a.copy()
    b[:2] = 0.5
    ma = np.zeros((8, 8), bool)
    ma[:2] = True
    m = image_metrics(a, ma, b, np.zeros((8, 8), bool))
    # union: 16 texels all off by 0.5 -> MSE 0.25; full image: 16 of 64 -> MSE 0.0625
    assert m["psnr_db_union_mask"] == m["psnr_db"] == pytest.approx(10 * np.log10(4), rel=1e-6)
    assert m["psnr_db_full"] == pytest.approx(10 * np.log10(16), rel=1e-6)
    assert m["ssim_union_mask"] == m["ssim"] and m["ssim"] < m["ssim_full"] < 1
    same = image_metrics(a, ma, a, ma)
    assert same["psnr_db_full"] == float("inf") and same["ssim_full"] == pytest.approx(1.0)


def test_evaluate_named_frames_and_cameras(setup, tmp_path):
    from uvatar.capture import Capture

    root, body, cap, _ = setup
    cam = list(Capture(cap).cameras())[1]
    m = evaluate_avatar(root / "avatar", cap, EvalConfig(progress=False, image_size=32, frames=("000005",),
                                                           cameras=(cam,), sheets_per_camera=True),
                        image_dir=tmp_path, body=body)
    assert m["frames"] == ["000005"] and m["camera_names"] == [cam] and m["cameras"] == 1
    assert m["split"] == "frames given" and "full image" in m["protocol"]
    for res in (m["avh"], *m["baselines"].values()):
        assert res["psnr_db"] == res["psnr_db_union_mask"] and res["ssim"] == res["ssim_union_mask"]
        # outside the union both images are the white background, so the full image scores higher (SSIM
        # windows straddling the union's edge mix both, hence the small tolerance there)
        assert res["psnr_db_full"] >= res["psnr_db"] and res["ssim_full"] >= res["ssim"] - 1e-3
    assert m["images"] == [str(tmp_path / f"000005_{cam}.png")] and (tmp_path / f"000005_{cam}.png").is_file()


@pytest.mark.parametrize("field,value,match", [("frames", ("000005", "999999"), "999999"),
                                               ("cameras", ("nope",), "nope")])
def test_evaluate_unknown_names_raise(setup, field, value, match):
    root, body, cap, _ = setup
    with pytest.raises(InputError, match=match):
        evaluate_avatar(root / "avatar", cap, EvalConfig(progress=False, **{field: value}), body=body)


def test_count_or_names():
    from uvatar.cli.avh import _count_or_names

    assert _count_or_names(None, "--frames") == (None, None)
    assert _count_or_names("3", "--frames") == (3, None)
    assert _count_or_names("03,07", "--cameras") == (None, ("03", "07"))
    assert _count_or_names("000054", "--frames") == (None, ("000054",))
    assert _count_or_names("cam1", "--cameras") == (None, ("cam1",))
    with pytest.raises(InputError, match="--frames"):
        _count_or_names(",", "--frames")


def test_cli_eval_named(setup, tmp_path, monkeypatch, capsys):
    import uvatar.body
    from uvatar.capture import Capture
    from uvatar.cli.main import main

    root, body, cap, _ = setup
    monkeypatch.setattr(uvatar.body, "load_body_model", lambda name, **kw: body)
    cams = list(Capture(cap).cameras())
    out = tmp_path / "m.json"
    assert main(["eval", "avh", str(root / "avatar"), str(cap), "--json", str(out), "--image-size", "32",
                 "--frames", "000005,000004", "--cameras", ",".join(cams[::-1]), "--images", str(tmp_path / "im"),
                 "--sheet-per-camera", "--report", str(tmp_path / "rep" / "eval.html")]) == 0
    m = json.loads(out.read_text())
    assert m["frames"] == ["000005", "000004"] and m["camera_names"] == cams[::-1]
    assert len(m["images"]) == 4 and np.isfinite(m["avh"]["psnr_db_full"])
    assert m["protocol"].startswith("the frames given (--frames")
    # the report: every method's row with the JSON's figures, the regions, the images linked from its folder
    page = (tmp_path / "rep" / "eval.html").read_text()
    for name in ("avh", "mean_texture", "nearest_pose"):
        assert f"<td>{name}</td>" in page
    assert f"<td>{m['avh']['psnr_db']:.4g}</td>" in page and "By body region" in page
    for image in m["images"]:
        rel = Path(os.path.relpath(Path(image).resolve(), tmp_path / "rep")).as_posix()
        assert f'src="{rel}"' in page and (tmp_path / "rep" / rel).is_file()
    assert "report at" in capsys.readouterr().out
    assert main(["eval", "avh", str(root / "avatar"), str(cap), "--frames", "000099"]) == 1
    assert main(["eval", "avh", str(root / "avatar"), str(cap), "--image-size", "0"]) == 1


def test_evaluate_uv_r2_distances_and_a_second_avatar(setup):
    from uvatar.avh.pose_metrics import pose_distance_deg

    root, body, cap, baked = setup
    m = evaluate_avatar(root / "avatar", cap, EvalConfig(progress=False, image_size=32, max_cameras=1,
                                                         pose_source="fit"), body=body, others={"twin": root / "avatar"})
    # the same avatar under another name scores the same
    for key in ("psnr_db", "geometry_mm", "texture_r2", "displacement_r2"):
        assert m["others"]["twin"][key] == pytest.approx(m["avh"][key])
    # known answer: the mean-texture baseline's texture is the mean map itself
    assert m["baselines"]["mean_texture"]["texture_r2"] == pytest.approx(0.0, abs=1e-9)
    assert all(np.isfinite(v[k]) for v in (m["avh"], *m["baselines"].values()) for k in ("texture_r2", "displacement_r2"))
    # the nearest-training-pose distance is the minimum over the training frames' poses
    train = json.loads((baked / "dataset.json").read_text())["selection"]["train"]
    poses = np.stack([load_frame(baked / "frames" / f"{f}.npz")["pose"] for f in train])
    for f in m["frames"]:
        d = pose_distance_deg(load_frame(baked / "frames" / f"{f}.npz")["pose"][None], poses, body.conditioning_joints)
        assert m["nearest_training_distance_deg"][f] == pytest.approx(d.min(), abs=1e-3)
    assert sorted(sum((b["frames"] for b in m["distance_bins"]), [])) == sorted(m["frames"])
    assert m["avatars"]["twin"]["conditioning"] == "global"
    json.dumps(m)


def _scans_only(cap, dst):
    """The toy capture as a real take comes: scans, fits and capture.json; no gt/, cameras or images."""
    import shutil

    shutil.copytree(cap, dst, ignore=shutil.ignore_patterns("gt", "cameras", "images", "masks"))
    return dst


def test_evaluate_a_scan_only_take_by_region_both_ways_and_against_its_own_bake(setup, tmp_path):
    from uvatar.body.masks import REGION_NAMES

    root, body, cap, baked = setup
    take = _scans_only(cap, tmp_path / "take")
    train = json.loads((baked / "dataset.json").read_text())["selection"]["train"]
    frames = ("000004", train[0])  # a held-out frame and a training frame
    m = evaluate_avatar(root / "avatar", take, EvalConfig(progress=False, frames=frames, orbit_views=2, orbit_size=48,
                                                          pose_source="fit"), body=body)
    assert "2 virtual cameras" in m["protocol"] and "48x48 px" in m["protocol"] and m["cameras"] == 2
    assert m["own_bake_frames"] == list(frames)
    for res in (m["avh"], *m["baselines"].values()):
        g = res["scan_geometry"]
        assert g["avatar_to_scan_mm"] >= 0 and g["scan_to_avatar_mm"] >= 0
        assert res["geometry_mm"] == pytest.approx(0.5 * (g["avatar_to_scan_mm"] + g["scan_to_avatar_mm"]))
        assert res["regions"] and set(res["regions"]) <= set(REGION_NAMES)  # the toy tube has no torso joint
        for values in res["regions"].values():
            assert {"psnr_db", "ssim", "psnr_db_inside_both", "chamfer_mm", "texture_r2_own_bake"} <= set(values)
    # known answer: on its own training frame, the nearest training pose is that frame: its maps are the
    # frame's own bake, so its texture R² against the own bake is 1 on that frame
    [entry] = [e for e in m["per_frame"] if e["frame"] == train[0]]
    assert entry["nearest_training_frame"] == train[0]
    assert entry["nearest_pose_texture_r2_own_bake"] == pytest.approx(1.0, abs=1e-6)
    assert m["baselines"]["mean_texture"]["texture_r2_own_bake"] < 1.0
    # the frame's own bake, rendered like the avatar: on the training frame it is the nearest pose itself
    assert entry["own_bake_psnr_db"] == pytest.approx(entry["nearest_pose_psnr_db"])
    assert "own_bake" in m["upper_bound"] and "own_bake_texture_r2_own_bake" not in entry
    # the time neighbour (a real take only): on a training frame it is that frame; on 000004 the training
    # frame nearest in frame number (the earlier on a tie)
    assert "nearest_time" in m["baselines"] and "nearest_time" in m["protocol"]
    assert entry["nearest_time_training_frame"] == train[0]
    assert entry["nearest_time_psnr_db"] == pytest.approx(entry["own_bake_psnr_db"])
    [held] = [e for e in m["per_frame"] if e["frame"] == "000004"]
    numbers = np.array([int(f) for f in train])
    best = numbers[np.abs(numbers - 4) == np.abs(numbers - 4).min()].min()
    assert held["nearest_time_training_frame"] == f"{best:06d}"
    json.dumps(m)



def test_frames_in_worker_processes_give_the_same_figures(setup, tmp_path):
    """--workers 2: each frame in a worker process (its context built there from the avatar and capture
    folders), the tallies merged in frame order: the same JSON as one process, on a scan-only take (scan
    geometry, R² against the own bakes, regions) and on the synthetic capture (R² against gt, the ceiling)."""
    root, body, cap, baked = setup
    take = _scans_only(cap, tmp_path / "take")
    train = json.loads((baked / "dataset.json").read_text())["selection"]["train"]
    cases = [(take, dict(frames=("000004", train[0]), orbit_views=2, orbit_size=40)),
             (cap, dict(image_size=32, max_cameras=1))]
    for capture, kw in cases:
        runs = [evaluate_avatar(root / "avatar", capture, EvalConfig(progress=False, pose_source="fit", workers=w, **kw),
                                body=body) for w in (1, 2)]
        one, two = (json.loads(json.dumps({k: v for k, v in m.items() if k != "config"})) for m in runs)
        assert len(one["per_frame"]) == 2
        assert two == one


def test_evaluate_reports_the_bake_ceiling_and_r2_against_the_own_bake(setup):
    root, body, cap, baked = setup
    m = evaluate_avatar(root / "avatar", cap, EvalConfig(progress=False, image_size=32, max_cameras=1,
                                                         pose_source="fit"), body=body)
    ceiling = m["bake_ceiling"]
    assert ceiling["frames"] == m["frames"]  # the toy bake holds the held-out frames too
    # the toy's bake is exact (its maps are the truth at the same texels): the ceiling is 1
    assert ceiling["texture_r2"] == pytest.approx(1.0, abs=1e-6)
    assert ceiling["displacement_r2"] == pytest.approx(1.0, abs=1e-6)
    # on the same frames the methods score as in the main table (every held-out frame has a bake)
    for key in ("texture_r2", "displacement_r2"):
        assert ceiling["methods_same_frames"]["avh"][key] == pytest.approx(m["avh"][key])
    # against an exact bake, the R² without gt is the R² against gt (texture at the same texels)
    assert m["avh"]["texture_r2_vs_bake"] == pytest.approx(m["avh"]["texture_r2"], abs=1e-6)
    assert m["baselines"]["mean_texture"]["texture_r2_vs_bake"] == pytest.approx(0.0, abs=1e-9)
    assert np.isfinite(m["avh"]["displacement_r2_vs_bake"])
    assert all("avh_displacement_r2_vs_bake" in e and "own_bake_displacement_r2" in e for e in m["per_frame"])
    json.dumps(m)
