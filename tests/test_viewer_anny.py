"""Engine bundle and viewer server on the real anny body (a random generator; no training)."""

from __future__ import annotations

import json
import urllib.request

import numpy as np
import pytest

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def anny_avatar(tmp_path_factory):
    from uvatar.body import load_body_model

    body = load_body_model("anny")  # a hard dependency: a failure fails the tests
    from tests.fixtures.toy_avatar import write_random_body_avatar

    out = tmp_path_factory.mktemp("anny_avatar")
    manifest = write_random_body_avatar(out, body, resolution=32, subdivisions=1)
    return out, manifest, body


def test_anny_bundle_counts_and_joints(anny_avatar):
    import trimesh

    out, manifest, body = anny_avatar
    assert manifest["mesh"]["triangles"] == 4 * len(body.template.faces)
    (geom,) = trimesh.load(out / "avatar.glb").geometry.values()
    assert len(geom.faces) == manifest["mesh"]["triangles"]
    assert manifest["joint_names"] == list(body.joint_names)
    assert manifest["pose_encoding"]["joints"] == list(body.conditioning_joints)
    assert set(manifest["semantic_joints"]) >= {"pelvis", "l_shoulder", "r_knee", "head"}
    import imageio.v3 as iio

    mask = iio.imread(out / "finger_toe_mask.png")
    assert mask.shape[:2] == (32, 32) and mask.max() == 255  # fingers and toes are masked


def test_retarget_endpoint_plays_the_cmu_clip_on_anny(anny_avatar, shared_data):
    from uvatar.viewer.server import ViewerConfig, ViewerServer

    bvh = shared_data / "motions" / "cmu_01_01.bvh"
    if not bvh.is_file():
        pytest.skip(f"{bvh} not found")
    out, manifest, body = anny_avatar
    with ViewerServer(out, ViewerConfig(port=0, open_browser=False, motions=(str(bvh),))) as server:
        req = urllib.request.Request(server.url + "api/retarget", data=bvh.read_bytes(), method="POST",
                                     headers={"X-Filename": bvh.name})
        motion = json.loads(urllib.request.urlopen(req, timeout=120).read())
        listing = json.loads(urllib.request.urlopen(server.url + "api/motions", timeout=10).read())
        assert listing == [{"name": "cmu_01_01", "url": "api/extra-motion/0"}]
        extra = json.loads(urllib.request.urlopen(server.url + listing[0]["url"], timeout=120).read())
    assert extra["poses"] == motion["poses"]
    poses = np.asarray(motion["poses"])
    assert motion["fps"] == 30 and poses.shape[1] == 3 * body.num_joints and len(poses) > 100
    assert np.abs(poses).max() > 0.1 and np.isfinite(poses).all()
    assert np.asarray(motion["Rh"]).shape == (len(poses), 3)
