"""The viewer with a rest-frame avatar, in headless Chromium (own module: Playwright's sync API
cannot nest inside test_viewer_browser's shared page session)."""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.viewer.browser import missing_browser_reason

pytestmark = pytest.mark.browser

REASON = missing_browser_reason()
if REASON:
    pytest.skip(f"browser tests skipped: {REASON}", allow_module_level=True)

from test_viewer_browser import _bilinear_clamped, generator_displacement  # noqa: E402

from tests.fixtures.toy_avatar import toy_rest_body, write_toy_avatar  # noqa: E402
from uvatar.viewer.browser import set_pose, viewer_page  # noqa: E402
from uvatar.viewer.server import ViewerConfig, ViewerServer  # noqa: E402


def test_rest_frame_displacement_is_added_before_skinning(tmp_path):
    """A rest-frame avatar (manifest displacement.frame "rest"): p = skin(p_rest + D), so the bones turn D."""
    import dataclasses

    import roma
    import torch

    from uvatar.avh.exporters.engine import EngineExportConfig, engine_mesh, skin_reference

    manifest = write_toy_avatar(tmp_path, resolution=32, displacement_frame="rest")
    assert manifest["displacement"]["frame"] == "rest" and manifest["displacement"]["applied"].startswith("before")
    pose = np.array([0, 0, 0.1, 0.2, 0, 0.9, 0, -0.4, 0.2, 0.5, 0.1, 0], np.float32)
    with ViewerServer(tmp_path, ViewerConfig(port=0, open_browser=False)) as server, \
            viewer_page(server.url, 320, 240) as page:
        set_pose(page, pose)
        mesh = engine_mesh(toy_rest_body(), EngineExportConfig(subdivisions=1))
        idx = np.random.default_rng(1).choice(len(mesh.positions), 200, replace=False)
        js = np.array(page.evaluate("i => window.uvatar.displacedVertices(i)", idx.tolist()))
    d = _bilinear_clamped(generator_displacement(tmp_path, manifest, pose), mesh.uv1)
    rots = roma.rotvec_to_rotmat(torch.as_tensor(pose.reshape(4, 3), dtype=torch.float64)).numpy()
    ref = skin_reference(dataclasses.replace(mesh, positions=mesh.positions + d), rots)[idx]
    after = skin_reference(mesh, rots)[idx] + d[idx]  # the body-frame rule gives another surface here
    assert np.abs(ref - after).max() > 1e-3
    np.testing.assert_allclose(js, ref, atol=2e-5)
