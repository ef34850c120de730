"""Training pose selection (AVH §3.4): k-means on joint-angle cosines, held-out frames, replacement of
rejected frames, and the `uvatar select` command on baked datasets and captures."""

from __future__ import annotations

import json

import numpy as np
import pytest

from uvatar.avh.bake.select import SelectConfig, pose_features, select_frames


def clustered_poses(n_clusters=5, per_cluster=20, joints=4, seed=0):
    """Poses (N, J*3) in well separated clusters; frame names and the cluster of each frame."""
    rng = np.random.default_rng(seed)
    centres = rng.uniform(0.2, 1.4, (n_clusters, joints * 3)) * np.sign(rng.normal(size=(n_clusters, joints * 3)))
    labels = np.repeat(np.arange(n_clusters), per_cluster)
    poses = centres[labels] + rng.normal(0, 0.02, (len(labels), joints * 3))
    names = [f"{i:06d}" for i in range(len(labels))]
    return names, poses, labels


def test_pose_features_are_cosines_of_the_conditioning_joints():
    poses = np.array([[0.0, 0.0, 0.0, np.pi, 0.5, -0.5]])
    np.testing.assert_allclose(pose_features(poses, [1]), [[-1.0, np.cos(0.5), np.cos(0.5)]])
    assert pose_features(poses, [0, 1], "sincos").shape == (1, 12)
    with pytest.raises(ValueError):
        pose_features(poses, [0], "tan")


def test_one_frame_per_cluster_nearest_to_its_centre():
    names, poses, labels = clustered_poses()
    sel = select_frames(names, poses, joints=range(4), config=SelectConfig(n_train=4, n_val=1, seed=0))
    chosen = sel.train + sel.val
    assert len(sel.train) == 4 and len(sel.val) == 1 and len(set(chosen)) == 5
    assert sorted(labels[[names.index(f) for f in chosen]]) == [0, 1, 2, 3, 4]   # one per pose cluster
    feats = pose_features(poses, range(4))
    for cl in sel.clusters:
        members = [names.index(f) for f in names if labels[names.index(f)] == labels[names.index(cl["candidates"][0])]]
        centre = feats[members].mean(0)
        best = members[int(np.argmin(((feats[members] - centre) ** 2).sum(1)))]
        assert cl["candidates"][0] == names[best]                           # the frame nearest the centre
        assert len(cl["candidates"]) == SelectConfig().candidates
    # deterministic for a seed
    again = select_frames(names, poses, joints=range(4), config=SelectConfig(n_train=4, n_val=1, seed=0))
    assert again.train == sel.train and again.val == sel.val


def test_excluded_frames_are_never_selected_and_small_inputs():
    names, poses, _ = clustered_poses(n_clusters=3, per_cluster=4)
    excluded = names[::2]
    sel = select_frames(names, poses, range(4), SelectConfig(n_train=5, n_val=1), exclude=excluded)
    chosen = set(sel.train + sel.val)
    assert not chosen & set(excluded)
    assert all(not set(cl["candidates"]) & set(excluded) for cl in sel.clusters)
    tiny = select_frames(names[:3], poses[:3], range(4), SelectConfig(n_train=10, n_val=2))
    assert sorted(tiny.train + tiny.val) == names[:3]                      # fewer frames than asked: all
    from uvatar.errors import InputError

    with pytest.raises(InputError):
        select_frames(names[:2], poses[:2], range(4), exclude=names[:2])


def test_bake_selection_replaces_rejected_frames(monkeypatch, tmp_path):
    """A selected frame that the bake rejects is replaced by the next nearest to its centre."""
    from uvatar.avh.bake import pipeline
    from uvatar.avh.bake.pipeline import FrameResult, bake_selection

    rejected = {"000000", "000007"}
    calls = []

    def fake_bake(capture_root, out_root, config, frames, workers, progress, overwrite, executor=None):
        calls.append(list(frames))
        return {f: FrameResult(f, "rejected" if f in rejected else "baked", "low kappa" if f in rejected else None)
                for f in frames}

    monkeypatch.setattr(pipeline, "bake_capture", fake_bake)
    monkeypatch.setattr(pipeline, "heldout_frames", lambda root: ["000001"])
    selection = {"clusters": [{"split": "train", "candidates": ["000000", "000001", "000002", "000003"]},
                              {"split": "train", "candidates": ["000005", "000006"]},
                              {"split": "val", "candidates": ["000007", "000002", "000008"]}]}
    out = bake_selection(tmp_path / "cap", tmp_path / "out", selection)
    assert out["train"] == ["000002", "000005"] and out["val"] == ["000008"]
    assert out["replaced"] == {"000000": "000002", "000007": "000008"} and out["unfilled"] == 0
    assert calls[0] == ["000000", "000005", "000007"] and "000001" not in sum(calls, [])
    info = json.loads((tmp_path / "out" / "dataset.json").read_text())
    assert info["selection"] == {"train": ["000002", "000005"], "val": ["000008"]}


def test_select_cli_on_baked_dataset_and_capture(tmp_path):
    from test_avh_bake_helpers import body

    from uvatar.capture import BodyFit, write_capture_info, write_fit
    from uvatar.cli.main import main
    from uvatar.io_utils import write_json, write_npz

    model = body()
    names, small, _ = clustered_poses(n_clusters=4, per_cluster=5, joints=len(model.conditioning_joints))
    poses = np.zeros((len(names), model.num_joints, 3), np.float32)
    poses[:, list(model.conditioning_joints)] = small.reshape(len(names), -1, 3)
    # a baked dataset (only the fields selection reads)
    baked = tmp_path / "baked"
    for name, pose in zip(names, poses, strict=True):
        write_npz(baked / "frames" / f"{name}.npz", pose=pose.reshape(-1))
    write_json(baked / "dataset.json", {"texels": 8, "frames_baked": names, "heldout_frames": [names[0]],
                                        "conditioning_joints": list(model.conditioning_joints)})
    assert main(["select", str(baked), "-n", "3", "--val", "1"]) == 0
    info = json.loads((baked / "dataset.json").read_text())
    assert len(info["selection"]["train"]) == 3 and len(info["selection"]["val"]) == 1
    assert names[0] not in info["selection"]["train"] + info["selection"]["val"]
    # a capture: fits only; one unreadable fit is skipped, held-out frames excluded
    cap = tmp_path / "cap"
    for name, pose in zip(names, poses, strict=True):
        write_fit(cap / "fits" / f"{name}.json", BodyFit(poses=pose.reshape(-1)))
    (cap / "fits" / f"{names[1]}.json").write_text("{broken")
    write_capture_info(cap, names)
    write_json(cap / "gt" / "info.json", {"heldout_frames": [names[2]], "broken_frames": []})
    assert main(["select", str(cap), "--from-capture", "-n", "3", "--val", "1", "-o", str(tmp_path / "s.json")]) == 0
    sel = json.loads((tmp_path / "s.json").read_text())
    chosen = sel["train"] + sel["val"]
    assert len(chosen) == 4 and names[1] not in chosen and names[2] not in chosen
    assert all(len(c["candidates"]) >= 1 for c in sel["clusters"])
    assert main(["select", str(tmp_path / "missing")]) == 1


def test_frames_in_range_is_half_open_on_take_numbers():
    from uvatar.capture.layout import frames_in_range, is_frame_range
    from uvatar.errors import InputError

    frames = [f"{i:06d}" for i in range(0, 150, 1)]
    assert frames_in_range(frames, "0:120") == frames[:120]
    assert frames_in_range(frames, "120:") == frames[120:] and frames_in_range(frames, ":3") == frames[:3]
    assert is_frame_range("120:150") and not is_frame_range("000120") and not is_frame_range("1,2")
    with pytest.raises(InputError, match=r"--frames: no frame in 200:300 \(the capture's frames are 0..149\)"):
        frames_in_range(frames, "200:300")
    with pytest.raises(InputError, match="is empty"):
        frames_in_range(frames, "5:5")


def test_select_from_baked_only_inside_the_range(tmp_path):
    from tests.fixtures.fake_baked import make_fake_baked_dataset
    from uvatar.avh.bake.select import select_from_baked

    root = make_fake_baked_dataset(tmp_path / "baked", num_frames=10)
    sel = select_from_baked(root, SelectConfig(n_train=3, n_val=1), frame_range="2:6")
    assert set(sel.train + sel.val) <= {"000002", "000003", "000004", "000005"} and len(sel.train) == 3
    info = json.loads((root / "dataset.json").read_text())
    assert info["selection_info"]["frame_range"] == "2:6" and info["selection"]["train"] == sel.train


def test_a_selection_made_before_its_inputs_changed_is_refused(tmp_path, capsys, monkeypatch):
    """A selection records the files it chose by: train avh refuses a dataset.json selection whose baked
    frames were rebaked or added since, and bake --frames-from refuses a selection.json whose fits were
    refitted since, in one line naming the file and the command that makes it again."""
    import os

    from test_avh_bake_helpers import body

    from uvatar.avh.bake import pipeline
    from uvatar.avh.data import selection
    from uvatar.capture import BodyFit, write_capture_info, write_fit
    from uvatar.cli.main import main
    from uvatar.errors import InputError
    from uvatar.io_utils import write_json, write_npz

    model = body()
    names, small, _ = clustered_poses(n_clusters=3, per_cluster=3, joints=len(model.conditioning_joints))
    poses = np.zeros((len(names), model.num_joints, 3), np.float32)
    poses[:, list(model.conditioning_joints)] = small.reshape(len(names), -1, 3)
    baked = tmp_path / "baked"
    for name, pose in zip(names[:-1], poses, strict=False):
        write_npz(baked / "frames" / f"{name}.npz", pose=pose.reshape(-1))
    write_json(baked / "dataset.json", {"texels": 8, "frames_baked": names[:-1], "heldout_frames": [],
                                        "conditioning_joints": list(model.conditioning_joints)})
    assert main(["select", str(baked), "-n", "2", "--val", "1"]) == 0
    meta = json.loads((baked / "dataset.json").read_text())
    assert len(meta["selection_info"]["inputs"]) == len(names) - 1
    train, val = selection(meta, baked)
    assert len(train) == 2 and len(val) == 1
    # a bake that grew by one frame since
    write_npz(baked / "frames" / f"{names[-1]}.npz", pose=poses[-1].reshape(-1))
    with pytest.raises(InputError, match=rf"dataset.json: the selection is stale: .*{names[-1]}.npz is new since it "
                                         rf"was made; run `uvatar select {baked}` again"):
        selection(meta, baked)
    capsys.readouterr()
    assert main(["train", "avh", str(baked), str(tmp_path / "run"), "--preset", "cpu-tiny", "--epochs", "1",
                 "--no-progress"]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("uvatar: error:")]
    assert len(err) == 1 and "the selection is stale" in err[0], err
    # a frame baked again (another mtime): stale too; selecting again makes it current
    assert main(["select", str(baked), "-n", "2", "--val", "1"]) == 0
    meta = json.loads((baked / "dataset.json").read_text())
    assert selection(meta, baked)
    st = (baked / "frames" / f"{names[0]}.npz").stat()
    os.utime(baked / "frames" / f"{names[0]}.npz", ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))
    with pytest.raises(InputError, match=rf"{names[0]}.npz changed since it was made"):
        selection(meta, baked)

    # selection.json from a capture's fits; a fit redone afterwards
    cap = tmp_path / "cap"
    for name, pose in zip(names, poses, strict=True):
        write_fit(cap / "fits" / f"{name}.json", BodyFit(poses=pose.reshape(-1)))
    write_capture_info(cap, names)
    sel_path = tmp_path / "s.json"
    assert main(["select", str(cap), "--from-capture", "-n", "2", "--val", "1", "-o", str(sel_path)]) == 0
    assert len(json.loads(sel_path.read_text())["inputs"]) == len(names)
    monkeypatch.setattr(pipeline, "bake_capture", lambda *a, **k: pytest.fail("baked from a stale selection"))
    write_fit(cap / "fits" / f"{names[1]}.json", BodyFit(poses=poses[0].reshape(-1)))
    capsys.readouterr()
    assert main(["bake", str(cap), str(tmp_path / "b2"), "--frames-from", str(sel_path), "--no-progress"]) == 1
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("uvatar: error:")]
    assert len(err) == 1 and f"{sel_path}: the selection is stale: " in err[0] and f"{names[1]}.json changed" \
        in err[0] and f"run `uvatar select {cap} --from-capture` again" in err[0], err
