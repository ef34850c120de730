"""uvatar.fit body half: keypoints on the body, projection, loss terms, the sequence fit, evaluation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from uvatar.body import load_body_model
from uvatar.fit.body_fit import BodyFitConfig, FitObservations, fit_body_sequence
from uvatar.fit.body_keypoints import BLAZEPOSE_NAMES, BodyKeypoints
from uvatar.fit.initialize import procrustes
from uvatar.fit.losses import ScanTerm, keypoint3d_term, signed_scan_cost, smoothness_term

pytestmark = pytest.mark.usefixtures("one_torch_thread")

SHAPE = np.array([0.35, 0.6, 0.5, 0.5, 0.7, 0.45], np.float32)   # anny phenotypes (not the default)


@pytest.fixture(scope="module")
def anny():
    return load_body_model("anny")


@pytest.fixture(scope="module")
def keypoints(anny):
    return BodyKeypoints(anny)


def _pose(anny, frames: int, seed: int, std: float = 0.2):
    rng = np.random.default_rng(seed)
    pose = np.zeros((frames, anny.num_joints, 3), np.float32)
    pose[:, list(anny.conditioning_joints)] = rng.normal(0, std, (frames, len(anny.conditioning_joints), 3))
    Rh = rng.normal(0, 0.4, (frames, 3)).astype(np.float32)
    Th = rng.normal(0, 0.3, (frames, 3)).astype(np.float32)
    return pose, Rh, Th


def _posed(anny, pose, Rh, Th, shape):
    with torch.no_grad():
        return anny.pose(torch.as_tensor(pose), Rh=torch.as_tensor(Rh), Th=torch.as_tensor(Th),
                         shape=torch.as_tensor(shape))


def test_anny_keypoints_come_from_its_coco_regressor(anny, keypoints):
    import anny as anny_pkg
    from anny.keypoints import KeypointsRegressor

    assert keypoints.names == BLAZEPOSE_NAMES and len(BLAZEPOSE_NAMES) == 33
    assert (keypoints.weights > 0).all()                       # anny places all 33
    reg = KeypointsRegressor.coco(anny.anny)
    pose, Rh, Th = _pose(anny, 2, 0)
    posed = _posed(anny, pose, Rh, Th, SHAPE)
    ours = keypoints(posed).numpy()
    theirs = torch.einsum("kv,bvc->bkc", reg.regression_weights.float(), posed.vertices).numpy()
    for name in ("nose", "left_shoulder", "right_hip", "left_knee", "right_ankle", "left_heel", "right_ear"):
        k = keypoints.names.index(name)
        assert np.abs(ours[:, k] - theirs[:, reg.labels.index(name)]).max() < 5e-4, name   # pruning: < 0.5 mm
    assert anny_pkg is not None
    rest = keypoints(anny.rest_pose())[0].numpy()
    for side, sign in (("left", 1), ("right", -1)):                # the person's left is +X
        for part in ("eye", "shoulder", "wrist", "hip", "ankle", "foot_index", "pinky"):
            assert sign * rest[keypoints.names.index(f"{side}_{part}"), 0] > 0.01


def test_generic_fallback_places_keypoints_from_joints_and_template(anny):
    kp = BodyKeypoints(anny, use_regressor=False)
    w = dict(zip(kp.names, kp.weights, strict=True))
    assert all(w[n] > 0 for n in kp.names)
    assert w["left_hip"] == 0.5 and w["left_pinky"] < 1      # biased / untracked: down-weighted
    rest = kp(anny.rest_pose())[0].numpy()
    nose, heel, toe = (rest[kp.names.index(n)] for n in ("nose", "left_heel", "left_foot_index"))
    assert nose[1] > 0.5 and nose[2] > 0.1                     # the face, in front
    assert heel[2] < toe[2] - 0.15 and heel[1] < -0.75          # heel behind the toes, at the floor
    only = BodyKeypoints(anny, names=("nose", "no_such_landmark"))
    assert only.weights.tolist() == [1.0, 0.0]


def test_pose_joints_and_subset_skinning_match_full_pose(anny):
    from uvatar.fit.skinning import SubsetSkinner

    pose, Rh, Th = _pose(anny, 3, 1, std=0.3)
    posed = _posed(anny, pose, Rh, Th, SHAPE)
    with torch.no_grad():
        jt = anny.pose_joints(torch.as_tensor(pose), Rh=torch.as_tensor(Rh), Th=torch.as_tensor(Th),
                              shape=torch.as_tensor(SHAPE))
        assert torch.allclose(jt, posed.joint_transforms, atol=1e-5)
        ids = np.arange(0, anny.template.num_vertices, 7)
        sk = SubsetSkinner(anny, ids)
        v, n = sk(jt, sk.rest(torch.as_tensor(SHAPE)))
    err = (v - posed.vertices[:, ids]).norm(dim=-1)
    assert err.mean() < 5e-4 and err.max() < 6e-3               # anny's LBS vs re-skinning the rest mesh
    cos = (n * posed.normals[:, ids]).sum(-1)
    assert cos.median() > 0.999 and (cos > 0.95).float().mean() > 0.95   # LBS-rotated rest normals


def test_projection_matches_opencv_and_passes_gradcheck():
    import cv2

    from uvatar.capture.types import Camera
    from uvatar.fit.projection import camera_tensors, project_cameras

    rng = np.random.default_rng(0)
    cams = [Camera(f"c{i}", K=[[500, 0, 120], [0, 510, 130], [0, 0, 1]], R=cv2.Rodrigues(rng.normal(size=3) * 0.2)[0],
                   T=[0.1, 0.2, 3.0], dist=[0.1, -0.05, 0.001, 0.002, 0.01]) for i in range(2)]
    P = rng.normal(size=(6, 3)) * 0.4
    ct = camera_tensors(cams, dtype=torch.float64)
    px, depth = project_cameras(torch.tensor(P), ct)
    for i, c in enumerate(cams):
        ref = cv2.projectPoints(P, cv2.Rodrigues(c.R)[0], c.T, c.K, c.dist)[0][:, 0]
        assert np.abs(ref - px[i].numpy()).max() < 1e-9
        assert np.allclose(depth[i].numpy(), c.world_to_camera(P)[:, 2])
    x = torch.tensor(P, requires_grad=True)
    assert torch.autograd.gradcheck(lambda p: project_cameras(p, ct)[0], (x,))  # the lens is a constant
    # per-frame cameras (F, C): frame f's points through frame f's cameras, lens included
    per = camera_tensors([cams, cams[::-1]], dtype=torch.float64)
    assert per.K.shape == (2, 2, 3, 3) and per.dist.shape == (2, 2, 5)
    two = torch.tensor(np.stack([P, P[::-1].copy()]))
    px2, depth2 = project_cameras(two, per)
    for f, (points, order) in enumerate(((P, cams), (P[::-1], cams[::-1]))):
        for c, cam in enumerate(order):
            ref = cv2.projectPoints(points, cv2.Rodrigues(cam.R)[0], cam.T, cam.K, cam.dist)[0][:, 0]
            assert np.abs(ref - px2[f, c].numpy()).max() < 1e-9
            assert np.allclose(depth2[f, c].numpy(), cam.world_to_camera(points)[:, 2])
    y = two.clone().requires_grad_(True)
    assert torch.autograd.gradcheck(lambda p: project_cameras(p, per)[0], (y,))


def _graph_nodes(tensor) -> int:
    seen, todo = set(), [tensor.grad_fn]
    while todo:
        node = todo.pop()
        if node is None or node in seen:
            continue
        seen.add(node)
        todo.extend(n for n, _ in node.next_functions)
    return len(seen)


def test_projection_through_many_views_is_one_batched_expression():
    """A sequence fit projects through F x C views (per-frame virtual cameras of the scans); the lens is
    applied to all of them in one expression, so the backward graph does not grow with the number of
    views (one slice per view made the backward quadratic in the frames: each slice's backward fills a
    zero tensor of the whole batch). Checked with a real lens and with none."""
    import cv2

    from uvatar.capture.types import Camera
    from uvatar.fit.projection import camera_tensors, project_cameras

    rng = np.random.default_rng(1)
    for dist in ([0.1, -0.05, 0.001, 0.002, 0.01], [0.0] * 5):
        nodes = []
        for frames in (2, 12):
            cams = [[Camera(f"c{i}", K=[[500, 0, 120], [0, 510, 130], [0, 0, 1]],
                            R=cv2.Rodrigues(rng.normal(size=3) * 0.2)[0], T=[0.1, 0.2, 3.0], dist=dist)
                     for i in range(4)] for _ in range(frames)]
            x = torch.tensor(rng.normal(size=(frames, 5, 3)) * 0.4, requires_grad=True)
            px, _ = project_cameras(x, camera_tensors(cams, dtype=torch.float64))
            assert px.shape == (frames, 4, 5, 2)
            nodes.append(_graph_nodes(px))
        assert nodes[0] == nodes[1], nodes


def test_scan_term_is_zero_on_the_bodys_own_surface(anny):
    pose, Rh, Th = _pose(anny, 2, 2)
    posed = _posed(anny, pose, Rh, Th, SHAPE)
    ids = np.arange(0, anny.template.num_vertices, 5)
    v, n = posed.vertices[:, ids], posed.normals[:, ids]
    scans = [(v[t].numpy(), n[t].numpy()) for t in range(2)]
    term = ScanTerm(scans, np.arange(len(ids)), scan_samples=len(ids), max_distance=0.1, device="cpu")
    term.refresh(v, n)
    cost = term(v, n, sigma=0.05, inside_tolerance=0.0, inside_weight=1.0)
    assert cost.shape == (2,) and float(cost.abs().max()) < 1e-10
    moved = v + 0.01 * n                                        # body 1 cm outside its scan
    term.refresh(moved, n)
    assert (term(moved, n, 0.05, 0.0, 1.0) > 5e-5).all()


def test_signed_scan_cost_tolerates_clothing_not_penetration():
    d = torch.tensor([0.03, -0.03, -0.01, 0.0])
    c = signed_scan_cost(d, sigma=0.05, inside_tolerance=0.02, inside_weight=0.5)
    assert c[3] == 0 and c[2] == 0                              # inside, within the clothing tolerance
    assert c[0] > 10 * c[1] > 0                                 # outside the scan costs far more


def test_missing_keypoints_are_ignored(anny, keypoints):
    pose, Rh, Th = _pose(anny, 2, 3)
    k3 = keypoints(_posed(anny, pose, Rh, Th, SHAPE))
    conf = torch.ones(k3.shape[:2])
    w = torch.as_tensor(keypoints.weights)
    bad = k3.clone()
    bad[:, 5:9] = 1e3
    conf_bad = conf.clone()
    conf_bad[:, 5:9] = 0
    assert float(keypoint3d_term(k3, bad, conf_bad, w, 0.05).abs().max()) < 1e-12
    # through the whole fit: NaN or wild keypoints at confidence 0 change nothing
    cfg = BodyFitConfig(iterations=(5, 5, 5, 5), fit_shape=False)
    clean = fit_body_sequence(anny, FitObservations(k3.numpy(), conf.numpy()), cfg)
    wild = bad.numpy().copy()
    wild[0, 5] = np.nan
    noisy = fit_body_sequence(anny, FitObservations(wild, conf_bad.numpy()), cfg)
    conf_drop = conf.numpy().copy()
    conf_drop[:, 5:9] = 0
    ref = fit_body_sequence(anny, FitObservations(k3.numpy(), conf_drop), cfg)
    assert np.isfinite(noisy.poses).all()
    assert np.allclose(noisy.poses, ref.poses, atol=1e-6) and np.allclose(noisy.Th, ref.Th, atol=1e-6)
    assert not np.allclose(clean.poses, ref.poses, atol=1e-6)


def test_fit_recovers_known_pose_and_shape(anny, keypoints):
    """Own keypoints plus the body's own surface as the scan: pose and shape come back."""
    from uvatar.geometry.distance import point_surface_distance

    pose, Rh, Th = _pose(anny, 2, 4, std=0.15)
    posed = _posed(anny, pose, Rh, Th, SHAPE)
    k3 = keypoints(posed).numpy()
    scans = [(posed.vertices[t].numpy(), posed.normals[t].numpy()) for t in range(2)]
    obs = FitObservations(k3, np.ones(k3.shape[:2], np.float32), scans=scans)
    seen = []
    cfg = BodyFitConfig(iterations=(20, 20, 120, 120), w_smooth=0.0, joints="conditioning", scan_inside_tolerance=0.0, scan_inside_weight=1.0,
                        w_shape_prior=1e-5,                  # a weak prior: the known shape is far from the mean
                        scan_body_vertices=800, scan_samples=800, refresh_every=5)   # a bare body: no clothing
    fit = fit_body_sequence(anny, obs, cfg, progress=lambda done, total, info: seen.append((done, total, info["stage"])))
    assert seen[-1][:2] == (280, 280) and [s[2] for s in seen] == ["global", "torso", "limbs"] + ["full"] * 24
    assert fit.poses.shape == pose.shape and fit.shape.shape == (6,) and fit.observed.all()
    assert np.all(fit.poses[:, [j for j in range(anny.num_joints) if j not in anny.conditioning_joints]] == 0)
    got = _posed(anny, fit.poses, fit.Rh, fit.Th, fit.shape)
    cj = list(anny.conditioning_joints)
    mpjpe = (got.joints[:, cj] - posed.joints[:, cj]).norm(dim=-1).mean() * 1000
    assert mpjpe < 15, f"MPJPE {float(mpjpe):.1f} mm"
    with torch.no_grad():
        zero = torch.zeros(1, anny.num_joints, 3)
        rest_fit = anny.pose(zero, shape=torch.as_tensor(fit.shape)).vertices[0]
        rest_true = anny.pose(zero, shape=torch.as_tensor(SHAPE)).vertices[0]
        rest_default = anny.rest_pose().vertices[0]
    shape_err = (rest_fit - rest_true).norm(dim=-1).mean() * 1000
    start_err = (rest_default - rest_true).norm(dim=-1).mean() * 1000
    assert shape_err < 8 and shape_err < 0.1 * start_err, (float(shape_err), float(start_err))   # 129 mm at the start
    d = point_surface_distance(scans[0][0][::20], got.vertices[0].numpy(), anny.template.faces) * 1000
    assert np.median(d) < 4


def test_torso_stage_ignores_the_arms_keypoints(anny, keypoints):
    """With the arms at rest in the torso stage, a raised arm's elbow and wrist points could only be
    reached by turning the collar: that stage does not see them; the limbs stage does."""
    from uvatar.fit.body_config import ARM_KEYPOINTS
    from uvatar.fit.problem import FitProblem

    pose, Rh, Th = _pose(anny, 2, 6, std=0.1)
    k3 = keypoints(_posed(anny, pose, Rh, Th, SHAPE)).numpy()
    arm = [BLAZEPOSE_NAMES.index(n) for n in ARM_KEYPOINTS]
    moved = k3.copy()
    moved[:, arm] += 0.3                                          # the arm points somewhere else
    conf = np.ones(k3.shape[:2], np.float32)
    problems = [FitProblem(anny, FitObservations(k, conf), BodyFitConfig()) for k in (k3, moved)]
    with torch.no_grad():
        posed = problems[0].pose(False)
        torso = [float(p.terms(posed, 1)["keypoints3d"].sum()) for p in problems]
        limbs = [float(p.terms(posed, 2)["keypoints3d"].sum()) for p in problems]
    assert torso[0] == torso[1] and torso[0] > 0
    assert limbs[1] > limbs[0] + 0.01                          # robust: each far point adds a bounded cost


def test_a_frame_without_observations_is_carried_by_its_neighbours(anny, keypoints):
    pose, Rh, Th = _pose(anny, 3, 5, std=0.15)
    pose[2] = pose[0] + 0.2 * (pose[2] - pose[0])              # a smooth motion through the gap
    pose[1] = 0.5 * (pose[0] + pose[2])
    Rh[2], Th[2] = Rh[0] + 0.05, Th[0] + 0.03
    Rh[1], Th[1] = Rh[0] + 0.025, Th[0] + 0.015
    posed = _posed(anny, pose, Rh, Th, SHAPE)
    k3 = keypoints(posed).numpy()
    conf = np.ones(k3.shape[:2], np.float32)
    conf[1] = 0
    k3[1] = np.nan
    fit = fit_body_sequence(anny, FitObservations(k3, conf), BodyFitConfig(iterations=(20, 20, 60, 40)))
    assert fit.observed.tolist() == [True, False, True]
    assert np.isfinite(fit.poses).all() and np.isfinite(fit.frame_loss).all()
    got = _posed(anny, fit.poses, fit.Rh, fit.Th, fit.shape)
    cj = list(anny.conditioning_joints)
    err = (got.joints[:, cj] - posed.joints[:, cj]).norm(dim=-1).mean(-1) * 1000
    assert err.max() < 60 and err[1] < 1.3 * err[[0, 2]].mean(), err   # the gap as good as its neighbours
    assert np.linalg.norm(fit.Th[1] - 0.5 * (fit.Th[0] + fit.Th[2])) < 0.02


def test_procrustes_and_smoothness_known_answers():
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(0)
    src = rng.normal(size=(6, 3))
    R = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_matrix()
    R_fit, t_fit = procrustes(src, src @ R.T + [1, 2, 3], np.ones(6))
    assert np.allclose(R_fit, R) and np.allclose(t_fit, [1, 2, 3])
    x = torch.zeros(3, 1, 3)
    x[2, 0, 0] = 1.0
    assert torch.allclose(smoothness_term(x), torch.tensor([0.0, 0.5, 0.5]))
    assert smoothness_term(x[:1]).tolist() == [0.0]
    x[2, 0, 0] = 1.0                                           # a cut in the sequence: robust cost is bounded
    assert float(smoothness_term(x, sigma=0.03).max()) < 0.5 * 0.03 ** 2 + 1e-9


def test_config_bounds_and_empty_input(anny):
    with pytest.raises(ValueError, match="iterations"):
        BodyFitConfig(iterations=(1, 2))
    with pytest.raises(ValueError, match="scan_inside_weight"):
        BodyFitConfig(scan_inside_weight=2.0)
    with pytest.raises(ValueError, match="no frames"):
        fit_body_sequence(anny, FitObservations(None, None))


def test_texture_stage_runs_after_full_and_moves_the_pose_only(anny, keypoints):
    """With photometric views (the body's own colours rendered with depth from two cameras) a
    'texture' stage follows 'full'; it reports the photo term, moves the pose and leaves the shape
    exactly where 'full' put it; with w_photo 0 the views are ignored."""
    from uvatar.fit.photometric import PhotoViews
    from uvatar.render.cameras import look_at_camera
    from uvatar.render.mesh_renderer import render_mesh

    pose, Rh, Th = _pose(anny, 2, 7, std=0.1)
    Rh[:] = 0.0
    Th[:] = [0.0, 0.9, 0.0]
    posed = _posed(anny, pose, Rh, Th, SHAPE)
    k3 = keypoints(posed).numpy()
    rest = anny.template.vertices
    colours = 0.5 + 0.5 * np.stack([np.sin(25 * rest[:, 0]), np.sin(25 * rest[:, 1]), np.cos(25 * rest[:, 2])], -1)
    cams = [look_at_camera(eye, (0.0, 0.9, 0.0), (0.0, 1.0, 0.0), 50.0, 96, 96, str(i))
            for i, eye in enumerate([(0.0, 1.0, 3.0), (2.5, 1.2, -1.5)])]
    views = []
    for t in range(2):
        r = [render_mesh(posed.vertices[t].numpy(), anny.template.faces, c, vertex_colors=colours) for c in cams]
        views.append(PhotoViews(np.stack([x.rgb for x in r]).astype(np.float32),
                                np.stack([x.depth for x in r]).astype(np.float32), cams))
    stages_seen = []
    cfg = dict(iterations=(10, 10, 20, 20), photo_iterations=20, refresh_every=10)
    obs = FitObservations(k3, np.ones(k3.shape[:2], np.float32), photo=views)
    fit = fit_body_sequence(anny, obs, BodyFitConfig(w_photo=1.0, **cfg),
                            progress=lambda d, n, info: stages_seen.append(info["stage"]))
    before = fit_body_sequence(anny, obs, BodyFitConfig(w_photo=1.0, **dict(cfg, photo_iterations=0)))
    assert stages_seen == ["global", "torso", "limbs", "full", "full", "texture", "texture"]  # refreshes every 10
    assert "photo" in fit.losses and np.isfinite(fit.losses["photo"]) and "photo" not in before.losses
    np.testing.assert_array_equal(fit.shape, before.shape)   # the texture stage leaves the shape alone
    assert np.abs(fit.poses - before.poses).max() > 1e-4      # and moves the pose
    plain = fit_body_sequence(anny, FitObservations(k3, np.ones(k3.shape[:2], np.float32)), BodyFitConfig(**cfg))
    off = fit_body_sequence(anny, obs, BodyFitConfig(w_photo=0.0, **cfg))  # the views are ignored
    np.testing.assert_array_equal(off.poses, plain.poses)


def test_hip_chain_turns_where_no_scan_places_the_hips(anny, keypoints):
    """anny's pelvis.L/.R bones carry the hips. Detected hips twisted by 20 deg against the rest
    of the body (a real person's hips against anny's rig; on the real recording the fit's hip line
    was off by 13 deg mean): held at rest ("rest") the fitted hip line cannot follow, free ("auto"
    without scans) it does; with a scan, "auto" keeps them at rest."""
    from scipy.spatial.transform import Rotation

    from uvatar.fit.body_config import fitted_joints, hip_chain_joints
    from uvatar.fit.problem import FitProblem

    names = anny.template.joint_names
    chain = hip_chain_joints(anny)
    assert sorted(names[j] for j in chain) == ["pelvis.L", "pelvis.R"]
    assert chain <= set(fitted_joints(anny, hip_chain=True)) and not chain & set(fitted_joints(anny))
    zero = np.zeros((2, anny.num_joints, 3), np.float32)
    shape = anny.default_shape().numpy()                # the shape stays (fit_shape=False)
    posed = _posed(anny, zero, zero[:, 0], zero[:, 0], shape)
    k3 = keypoints(posed).numpy()
    left, right = BLAZEPOSE_NAMES.index("left_hip"), BLAZEPOSE_NAMES.index("right_hip")
    centre = (k3[:, left] + k3[:, right]) / 2
    twist = Rotation.from_rotvec([0.0, np.radians(20.0), 0.0])
    for k in (left, right):
        k3[:, k] = twist.apply(k3[:, k] - centre) + centre
    obs = FitObservations(k3, np.ones(k3.shape[:2], np.float32))

    def yaw(p):
        d = p[:, left] - p[:, right]
        return np.degrees(np.arctan2(d[:, 2], d[:, 0]))

    err = {}
    for mode in ("rest", "auto"):
        cfg = BodyFitConfig(iterations=(20, 60, 120, 60), w_smooth=0.0, fit_shape=False, hip_chain=mode)
        assert (chain <= set(FitProblem(anny, obs, cfg).joints)) == (mode == "auto")
        fit = fit_body_sequence(anny, obs, cfg)
        got = keypoints(_posed(anny, fit.poses, fit.Rh, fit.Th, fit.shape)).numpy()
        err[mode] = float(np.abs(yaw(got) - yaw(k3)).mean())
    assert err["auto"] < 6 and err["rest"] > 1.5 * err["auto"], err    # measured 3.2 and 8.8 deg
    scan = [(posed.vertices[t].numpy(), posed.normals[t].numpy()) for t in range(2)]
    with_scan = FitObservations(k3, obs.keypoints3d_conf, scans=scan)
    assert not chain & set(FitProblem(anny, with_scan, BodyFitConfig(hip_chain="auto")).joints)
    with pytest.raises(ValueError, match="hip_chain"):
        BodyFitConfig(hip_chain="loose")
