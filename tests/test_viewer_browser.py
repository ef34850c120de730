"""The viewer in real headless Chromium (Debian ``chromium`` driven by Playwright's Python API).

Skipped, with the reason, where playwright or chromium is missing. One page is shared by the tests.
"""

from __future__ import annotations

import json

import numpy as np
import pytest

from uvatar.viewer.browser import missing_browser_reason

pytestmark = pytest.mark.browser

REASON = missing_browser_reason()
if REASON:
    pytest.skip(f"browser tests skipped: {REASON}", allow_module_level=True)

from tests.fixtures.toy_avatar import toy_rest_body, write_toy_avatar  # noqa: E402
from tests.fixtures.viewer_page import canvas_pixels, run_generator_in_browser, wait_for_page  # noqa: E402
from uvatar.avh.exporters.engine import pose_to_model_input, posed_joint_transforms, run_generator  # noqa: E402
from uvatar.errors import UvatarError  # noqa: E402
from uvatar.viewer.browser import (  # noqa: E402
    call_page,
    set_pose,
    viewer_page,
    wait_idle,
)
from uvatar.viewer.server import ViewerConfig, ViewerServer  # noqa: E402


@pytest.fixture(scope="module")
def avatar(tmp_path_factory):
    out = tmp_path_factory.mktemp("toy_avatar")
    manifest = write_toy_avatar(out, resolution=32)
    return out, manifest


@pytest.fixture(scope="module")
def page(avatar):
    with ViewerServer(avatar[0], ViewerConfig(port=0, open_browser=False)) as server, \
            viewer_page(server.url, 480, 400) as page:
        yield page


def _changed_fraction(a, b, threshold=8):
    return float((np.abs(a.astype(int) - b.astype(int)).max(-1) > threshold).mean())


def test_page_loads_the_avatar(page, avatar):
    assert page.evaluate("window.uvatar.ready") is True
    assert page.evaluate("window.uvatar.error") is None
    assert page.evaluate("window.uvatar.manifest.texels") == avatar[1]["texels"]
    stats = page.evaluate("window.uvatar.stats")
    assert stats["backend"] in ("wasm", "webgpu") and stats["inferences"] >= 1 and stats["inferenceMs"] > 0
    assert "inference" in page.locator("#stats").inner_text()
    if stats["backend"] == "wasm":  # Chromium without --enable-unsafe-webgpu: no adapter, and the page says so
        assert "WebGPU" in stats["backendNote"] and stats["backendNote"] in page.locator("#stats").inner_text()


def test_canvas_is_not_blank(page):
    img = canvas_pixels(page)
    background = np.array([0xDF, 0xE3, 0xE8])
    foreground = np.abs(img.astype(int) - background).max(-1) > 12
    assert 0.02 < foreground.mean() < 0.9, foreground.mean()
    assert img[foreground].std() > 5  # textured, not a flat silhouette


def test_pose_slider_changes_the_avatar_pixels(page):
    set_pose(page, np.zeros(12))
    before = canvas_pixels(page)
    page.select_option("#joint-select", "1")
    page.locator("#slider-z").fill("0.8")
    wait_idle(page)
    after = canvas_pixels(page)
    assert page.evaluate("window.uvatar.getPose()")[3 * 1 + 2] == pytest.approx(0.8, abs=0.01)  # range step 0.01 from -pi
    assert _changed_fraction(before, after) > 0.01


def test_displacement_moves_the_surface(page):
    set_pose(page, np.zeros(12))
    try:
        page.evaluate("window.uvatar.setDisplacementScale(0)")
        wait_idle(page)
        bare = canvas_pixels(page)
        page.evaluate("window.uvatar.setDisplacementScale(4)")
        wait_idle(page)
        displaced = canvas_pixels(page)
    finally:
        page.evaluate("window.uvatar.setDisplacementScale(1)")
    assert _changed_fraction(bare, displaced) > 0.002


def test_browser_generator_matches_python_onnxruntime(page, avatar):
    out, manifest = avatar
    rng = np.random.default_rng(7)
    io_names = {"input": manifest["generator"]["input"], "texture": manifest["generator"]["texture_output"],
                "displacement": manifest["generator"]["displacement_output"]}
    for _ in range(3):
        pose = rng.uniform(-1.5, 1.5, 12).astype(np.float32)
        tex_js, disp_js, ms = run_generator_in_browser(page, pose)
        tex_py, disp_py = run_generator(out / "model.onnx", io_names,
                                        pose_to_model_input(pose[None], manifest["pose_encoding"]))
        assert tex_js.shape == tex_py.shape == (1, 3, 32, 32)
        assert np.abs(tex_js - tex_py).max() <= 1e-3
        assert np.abs(disp_js - disp_py).max() <= 1e-3
        assert ms > 0


def test_motion_plays_and_drives_the_generator(page):
    options = page.locator("#motion-select option").all_inner_texts()
    assert options[0].startswith("sway (built-in)") and "sway" in options[1:]  # + AVATAR/motions/sway.json
    before = page.evaluate("window.uvatar.stats.inferences")
    try:
        page.select_option("#motion-select", index=1)
        page.click("#play")
        wait_for_page(page, "window.uvatar.isPlaying()", what="the motion playing")
        # several inferences, each for a pose the playback set (not a fixed sleep: under load they are slow)
        wait_for_page(page, f"window.uvatar.stats.inferences > {before} + 2", what="inferences during playback")
        poses = [page.evaluate("window.uvatar.getPose()")]
        wait_for_page(page, f"window.uvatar.getPose().some((v, i) => v !== {poses[0]}[i])", what="the pose moving")
        poses.append(page.evaluate("window.uvatar.getPose()"))
    finally:
        page.click("#stop")
    assert page.evaluate("window.uvatar.isPlaying()") is False
    assert page.evaluate("window.uvatar.stats.inferences") > before + 2
    assert max(np.abs(poses[0]).max(), np.abs(poses[1]).max()) > 0.01
    assert np.abs(np.subtract(poses[0], poses[1])).max() > 0
    wait_idle(page)  # the last playback inference lands; the next test starts from a quiet page


def _root_state(page):
    return page.evaluate("""() => ({ offset: window.uvatar.avatarOffset(), target: window.uvatar.cameraTarget(),
                                     root: window.uvatar.jointWorldPositions()[0] })""")


def test_a_motions_root_path_walks_the_avatar_and_the_camera_follows(page):
    """Th moves the avatar from the first frame's place (V = R(Rh) X + Th), the orbit camera following;
    "in place" keeps only the height; stop puts both back."""
    frames = 90
    Th = [[0.8 * i / 30, 1.0 + 0.1 * i / frames, 5.0] for i in range(frames)]  # 0.8 m/s along x, rising 10 cm
    body = {"name": "walk-x", "fps": 30, "poses": [[0.0] * 12] * frames, "Rh": [[0.0, 0.0, 0.0]] * frames, "Th": Th}
    wait_idle(page)
    rest = _root_state(page)
    assert rest["offset"] == [0, 0, 0]
    try:
        page.evaluate("(body) => window.uvatar.playMotionJson(body)", body)
        wait_for_page(page, "window.uvatar.avatarOffset()[0] > 0.2", what="the avatar walking along +x")
        moved = _root_state(page)
    finally:
        page.click("#stop")
    x, y, z = moved["offset"]
    assert 0.2 < x < 2.4 and abs(z) < 1e-5  # from the first frame's place: Th[0]'s 5 m along z is not a jump
    assert y == pytest.approx(x / 0.8 * 30 / frames * 0.1, abs=2e-3)  # the height follows Th too
    assert np.allclose(np.subtract(moved["root"], rest["root"]), moved["offset"], atol=1e-5)
    shift = np.subtract(moved["target"], rest["target"])
    assert np.allclose(shift, [x, 0, 0], atol=1e-5)  # the camera follows horizontally
    stopped = _root_state(page)
    assert stopped["offset"] == [0, 0, 0] and np.allclose(stopped["target"], rest["target"], atol=1e-6)

    page.check("#in-place")
    try:
        page.evaluate("(body) => window.uvatar.playMotionJson(body)", body)
        wait_for_page(page, "window.uvatar.avatarOffset()[1] > 0.02", what="the avatar rising in place")
        held = _root_state(page)
    finally:
        page.click("#stop")
        page.uncheck("#in-place")
    assert held["offset"][0] == 0 and held["offset"][2] == 0 and np.allclose(held["target"], rest["target"], atol=1e-6)
    wait_idle(page)


def test_stalled_page_call_fails_with_a_clear_message(page):
    with pytest.raises(UvatarError, match=r"viewer call 'never' failed: .*no answer within 300 ms.*console"):
        call_page(page, "() => new Promise(() => {})", timeout_s=0.3, what="never")
    with pytest.raises(UvatarError, match="never reached 'false' within"):
        wait_for_page(page, "false", timeout_s=0.3, what="false")
    # whenIdle itself rejects (with the viewer state) when an inference never finishes
    message = page.evaluate("""async () => {
        window.uvatar.setPose(window.uvatar.getPose());  // pending, then busy for one inference
        try { await window.uvatar.whenIdle(0); return 'resolved'; } catch (e) { return e.message; }
    }""")
    assert message == "resolved" or "not idle after 0 ms (busy=" in message
    wait_idle(page)


@pytest.mark.parametrize("kind", ["angles", "sincos"])
def test_js_pose_encoding_matches_python_twin(page, kind):
    pose = np.random.default_rng(3).uniform(-3, 3, 12).astype(np.float32)
    encoding = {"type": kind, "joints": [3, 1]}
    js = np.array(page.evaluate("([p, e]) => window.uvatar.encodePose(p, e)", [pose.tolist(), encoding]))
    np.testing.assert_allclose(js, pose_to_model_input(pose, encoding), atol=1e-6)


def test_viewer_skeleton_matches_gltf_reference(page):
    import roma
    import torch

    pose = np.array([0, 0, 0.2, 0.3, 0, 0.1, 0, -0.4, 0.2, 0.5, 0.1, 0], np.float32)
    set_pose(page, pose)
    js = np.array(page.evaluate("window.uvatar.jointWorldPositions()"))
    body = toy_rest_body()
    rots = roma.rotvec_to_rotmat(torch.as_tensor(pose.reshape(4, 3), dtype=torch.float64)).numpy()
    ref = posed_joint_transforms(body.joint_world_rest, body.joint_parents, rots)[:, :3, 3]
    np.testing.assert_allclose(js, ref, atol=1e-5)


def _bilinear_clamped(image, uv_gltf):
    """(R, R, C) image with row 0 at glTF t = 0; (N, 2) glTF UVs -> (N, C), texel centres, clamp to edge."""
    R = image.shape[0]
    x = np.clip(uv_gltf[:, 0] * R - 0.5, 0, R - 1)
    y = np.clip(uv_gltf[:, 1] * R - 0.5, 0, R - 1)
    x0, y0 = np.floor(x).astype(int), np.floor(y).astype(int)
    x1, y1 = np.minimum(x0 + 1, R - 1), np.minimum(y0 + 1, R - 1)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    top = image[y0, x0] * (1 - fx) + image[y0, x1] * fx
    bottom = image[y1, x0] * (1 - fx) + image[y1, x1] * fx
    return top * (1 - fy) + bottom * fy


def generator_displacement(out, manifest, pose):
    """(R, R, 3) displacement map the avatar's ONNX generator gives for ``pose``, times (1 - finger/toe
    mask), row 0 at glTF t = 0: what the viewer uploads."""
    import imageio.v3 as iio

    io_names = {"input": "pose_angles", "texture": "texture", "displacement": "displacement"}
    _, disp = run_generator(out / "model.onnx", io_names, pose_to_model_input(pose[None], manifest["pose_encoding"]))
    keep = 1.0 - iio.imread(out / manifest["finger_toe_mask"]).astype(np.float32)[..., None] / 255.0
    return disp[0].transpose(1, 2, 0) * keep  # row 0 is v = 1, i.e. glTF t = 0


def test_displaced_vertices_match_python_reference(page, avatar):
    """Skinning + displacement sampled at TEXCOORD_1 after skinning, times (1 - finger/toe mask)."""
    import roma
    import torch

    from uvatar.avh.exporters.engine import EngineExportConfig, engine_mesh, skin_reference

    out, manifest = avatar
    pose = np.array([0, 0, 0.1, 0.2, 0, 0.3, 0, -0.4, 0.2, 0.5, 0.1, 0], np.float32)
    set_pose(page, pose)
    mesh = engine_mesh(toy_rest_body(), EngineExportConfig(subdivisions=1))  # the GLB's arrays
    idx = np.random.default_rng(0).choice(len(mesh.positions), 200, replace=False)
    js = np.array(page.evaluate("i => window.uvatar.displacedVertices(i)", idx.tolist()))
    dmap = generator_displacement(out, manifest, pose)
    rots = roma.rotvec_to_rotmat(torch.as_tensor(pose.reshape(4, 3), dtype=torch.float64)).numpy()
    ref = skin_reference(mesh, rots)[idx] + _bilinear_clamped(dmap, mesh.uv1[idx])
    assert np.abs(dmap).max() > 1e-3  # the toy really displaces
    np.testing.assert_allclose(js, ref, atol=2e-5)


def test_idle_wait_does_not_need_animation_frames(page):
    """whenIdle resolves from the inference itself even while requestAnimationFrame is stalled (runs last)."""
    page.evaluate("() => { window.__raf = window.requestAnimationFrame; window.requestAnimationFrame = () => 0; }")
    try:
        n = page.evaluate("window.uvatar.stats.inferences")
        set_pose(page, np.full(12, 0.05), timeout_s=30)
        assert page.evaluate("window.uvatar.stats.inferences") > n
    finally:
        page.evaluate("() => { window.requestAnimationFrame = window.__raf; }")


@pytest.mark.slow
def test_screenshot_module_writes_png_and_reports_inference(avatar, tmp_path):
    import subprocess
    import sys

    import imageio.v3 as iio

    png = tmp_path / "shot.png"
    # a separate process: Playwright's sync API cannot nest inside the page fixture's session
    proc = subprocess.run([sys.executable, "-m", "uvatar.viewer.screenshot", str(avatar[0]), str(png),
                           "--joint", "head=0.4,0,0", "--bench", "3", "--width", "320", "--height", "240"],
                          capture_output=True, text=True, timeout=240)
    assert proc.returncode == 0, proc.stderr[-2000:]
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["inference_ms"] > 0 and result["benchmark"]["n"] == 3
    assert result["pose_nonzero_joints"] == ["head"]
    assert iio.imread(png).shape[:2] == (240, 320)

