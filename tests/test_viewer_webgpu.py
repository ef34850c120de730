"""WebGPU in the viewer: headless Chromium with WebGPU on (SwiftShader's adapter where there is no GPU)
picks onnxruntime-web's WebGPU execution provider, says so on screen, and its maps match the wasm
backend's and Python's onnxruntime; the fp16 graph runs where asked and stays within the export's
fp16 tolerance.

Skipped, with the reason, where playwright or chromium is missing. SwiftShader's WebGPU is correct,
not fast: timings are for bench/viewer_webgpu.py, never asserted here.
"""

from __future__ import annotations

import numpy as np
import pytest

from uvatar.viewer.browser import missing_browser_reason

pytestmark = pytest.mark.browser

REASON = missing_browser_reason()
if REASON:
    pytest.skip(f"browser tests skipped: {REASON}", allow_module_level=True)

from tests.fixtures.toy_avatar import write_toy_avatar  # noqa: E402
from tests.fixtures.viewer_page import run_generator_in_browser, wait_for_page  # noqa: E402
from uvatar.avh.export import FP16_TOLERANCE  # noqa: E402
from uvatar.avh.exporters.engine import pose_to_model_input, run_generator  # noqa: E402
from uvatar.viewer.browser import viewer_page  # noqa: E402
from uvatar.viewer.server import ViewerConfig, ViewerServer  # noqa: E402

#: WebGPU (f32 shaders) against wasm and against Python's onnxruntime, max abs difference
WEBGPU_TOLERANCE = 1e-4


@pytest.fixture(scope="module")
def avatar(tmp_path_factory):
    out = tmp_path_factory.mktemp("toy_avatar_fp16")
    manifest = write_toy_avatar(out, resolution=32, fp16=True)
    return out, manifest


class Pages:
    """Viewer pages by query, opened when first asked for in one Chromium with WebGPU on. Only one
    WebGPU page lives at a time: a second one beside a busy first stalled SwiftShader's GPU process on
    CI (its adapter request never answered), so asking for another WebGPU page closes the open one."""

    def __init__(self, server, auto_page):
        self.server, self.browser = server, auto_page.context.browser
        self.open = {"": auto_page}

    @staticmethod
    def _uses_webgpu(query):
        return "ep=wasm" not in query

    def __getitem__(self, query):
        if query not in self.open:
            if self._uses_webgpu(query):
                for other in [q for q in self.open if self._uses_webgpu(q)]:
                    self.open.pop(other).close()
            page = self.browser.new_page(viewport={"width": 480, "height": 400})
            page.uvatar_logs = []
            page.on("console", lambda msg: page.uvatar_logs.append(f"{msg.type}: {msg.text}"))
            page.on("pageerror", lambda err: page.uvatar_logs.append(f"pageerror: {err}"))
            page.goto(self.server.url + query)
            wait_for_page(page, "window.uvatar && (window.uvatar.ready || window.uvatar.error)", 120, "ready")
            assert page.evaluate("window.uvatar.error") is None
            self.open[query] = page
        return self.open[query]


@pytest.fixture(scope="module")
def pages(avatar):
    """Pages of one Chromium with WebGPU on, by query ("" is the viewer's own choice)."""
    with ViewerServer(avatar[0], ViewerConfig(port=0, open_browser=False)) as server, \
            viewer_page(server.url, 480, 400, webgpu=True) as auto:
        yield Pages(server, auto)


def _poses(n=3):
    rng = np.random.default_rng(3)
    return [rng.uniform(-0.6, 0.6, 4 * 3) for _ in range(n)]  # TOY_JOINTS: 4 joints


def test_auto_picks_webgpu_and_says_so(pages, avatar):
    stats = pages[""].evaluate("window.uvatar.stats")
    assert stats["backend"] == "webgpu" and stats["inferences"] >= 1
    assert "swiftshader" in stats["adapter"] or stats["adapter"]  # a GPU's name where there is one
    text = pages[""].locator("#stats").inner_text()
    assert "WebGPU" in text and stats["precision"] in text
    if "swiftshader" in stats["adapter"]:  # no shader-f16 on SwiftShader: the fp32 graph, and why
        assert stats["precision"] == "fp32" and "shader-f16" in stats["backendNote"] and "shader-f16" in text
    assert avatar[1]["generator"]["file_fp16"] == "model_fp16.onnx"


def test_webgpu_maps_match_wasm_and_python(pages, avatar):
    assert pages["?ep=wasm"].evaluate("window.uvatar.stats.backend") == "wasm"
    manifest = avatar[1]
    for pose in _poses(2):
        gpu_tex, gpu_disp, _ = run_generator_in_browser(pages[""], pose)
        cpu_tex, cpu_disp, _ = run_generator_in_browser(pages["?ep=wasm"], pose)
        model_input = pose_to_model_input(pose, manifest["pose_encoding"])[None]
        ref_tex, ref_disp = run_generator(avatar[0] / "model.onnx", {"input": manifest["generator"]["input"],
                                          "texture": "texture", "displacement": "displacement"}, model_input)
        assert np.abs(gpu_tex - cpu_tex).max() <= WEBGPU_TOLERANCE
        assert np.abs(gpu_disp - cpu_disp).max() <= WEBGPU_TOLERANCE
        assert np.abs(gpu_tex - ref_tex).max() <= WEBGPU_TOLERANCE
        assert gpu_tex.std() > 0.05  # a real map, not zeros on both sides


@pytest.mark.parametrize("query", ["?ep=wasm&precision=fp16", "?ep=webgpu&precision=fp16"])
def test_fp16_graph_in_the_browser_is_close_to_fp32(pages, query):
    """fp16 on WebGPU needs the adapter's shader-f16 (SwiftShader has none: onnxruntime-web then returns
    wrong maps, so the viewer runs the fp16 graph on wasm and says why)."""
    page = pages[query]
    stats = page.evaluate("window.uvatar.stats")
    assert stats["precision"] == "fp16"
    if query.startswith("?ep=webgpu") and "shader-f16" in stats["backendNote"]:
        assert stats["backend"] == "wasm" and "shader-f16" in page.locator("#stats").inner_text()
    else:
        assert stats["backend"] == query.split("&")[0].split("=")[1]
    worst = {"texture": 0.0, "displacement": 0.0}
    for pose in _poses(2):
        tex16, disp16, _ = run_generator_in_browser(page, pose)
        tex, disp, _ = run_generator_in_browser(pages["?ep=wasm"], pose)
        worst["texture"] = max(worst["texture"], float(np.abs(tex16 - tex).max()))
        worst["displacement"] = max(worst["displacement"], float(np.abs(disp16 - disp).max()))
    assert all(0 < worst[k] <= FP16_TOLERANCE[k] for k in worst), worst  # > 0: it ran in half


def test_a_stalled_adapter_request_falls_back_to_wasm_and_says_so(pages):
    """A GPU process that never answers (as SwiftShader's did on a loaded CI machine) costs the page the
    adapter timeout, then the viewer runs on wasm and the note says why."""
    page = pages.browser.new_page(viewport={"width": 480, "height": 400})
    try:
        page.add_init_script("window.UVATAR_ADAPTER_TIMEOUT_MS = 500;"
                             "navigator.gpu.requestAdapter = () => new Promise(() => {});")
        page.goto(pages.server.url)
        wait_for_page(page, "window.uvatar && (window.uvatar.ready || window.uvatar.error)", 120, "ready")
        stats = page.evaluate("window.uvatar.stats")
        assert page.evaluate("window.uvatar.error") is None
        assert stats["backend"] == "wasm" and "timed out" in stats["backendNote"]
        assert "timed out" in page.locator("#stats").inner_text()
    finally:
        page.close()
