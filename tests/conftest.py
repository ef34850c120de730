"""Shared pytest fixtures. Tests run on CPU at 64–256 texels; GPU tests are marked ``gpu``."""

from __future__ import annotations

from pathlib import Path

import pytest

SHARED_DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"


def pytest_collection_modifyitems(config, items):
    try:
        import torch

        has_cuda = torch.cuda.is_available()
    except Exception:  # pragma: no cover
        has_cuda = False
    if not has_cuda:
        skip = pytest.mark.skip(reason="needs a CUDA GPU")
        for item in items:
            if "gpu" in item.keywords:
                item.add_marker(skip)


@pytest.fixture(scope="session")
def shared_data() -> Path:
    if not SHARED_DATA.is_dir():
        pytest.skip(f"shared data folder not found at {SHARED_DATA}")
    return SHARED_DATA


@pytest.fixture(scope="module")
def one_torch_thread():
    """One torch thread for a module (``pytestmark = pytest.mark.usefixtures("one_torch_thread")``):
    small ops on a shared 2-core machine are far faster without OpenMP."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def trained_toy_avatar():
    """Factory ``(root, num_frames, heldout=2) -> (body, capture_dir, baked_dir)``: a toy tube capture
    (:func:`tests.fixtures.toy_capture.make_toy_capture`, 32 texels), one AVH epoch on it (ROOT/run) and the
    exported avatar (ROOT/avatar), all on :class:`uvatar.body.toy.ToyTubeBody`."""

    def make(root, num_frames: int, heldout: int = 2):
        from tests.fixtures.toy_capture import make_toy_capture
        from uvatar.avh.export import export_avatar
        from uvatar.avh.model import AvhConfig
        from uvatar.avh.train import TrainConfig, train_avh
        from uvatar.body.toy import ToyTubeBody

        body = ToyTubeBody()
        cap, baked = make_toy_capture(root, body, num_frames=num_frames, heldout=heldout, resolution=32)
        train_avh(baked, root / "run", AvhConfig(4, 32, resolution=32),
                  TrainConfig(epochs=1, progress=False, tensorboard=False), body=body)
        export_avatar(root / "run", root / "avatar", body=body)
        return body, cap, baked

    return make


@pytest.fixture(scope="session")
def fit_studio(tmp_path_factory):
    """A small studio capture for the fit tests (2 frames, 4 cameras, 256^2 images, seed 0; ~10 s):
    ``(root, true_joints)`` with true_joints ``{frame: (J, 3) world joint positions}`` of the true
    (noise-free) pose from ``gt/frames``, and the anny body's ``semantic_joints`` under key "semantic"."""
    import numpy as np
    import torch

    from uvatar.body import load_body_model
    from uvatar.capture import Capture
    from uvatar.capture.synth.config import preset
    from uvatar.capture.synth.pipeline import synthesize

    root = tmp_path_factory.mktemp("fit_studio") / "cap"
    synthesize(root, preset("quick", frames=2, cameras=4, image_size=256, seed=0, preview=False),
               progress=False)
    cap = Capture(root)
    body = load_body_model("anny")
    shape = torch.tensor(np.asarray(cap.info["body_model"]["shapes"], np.float32))
    joints = {}
    for frame in cap.frames:
        g = np.load(root / "gt" / "frames" / f"{frame}.npz")
        with torch.no_grad():
            posed = body.pose(torch.tensor(g["pose"], dtype=torch.float32).view(1, -1, 3),
                              torch.tensor(g["Rh"], dtype=torch.float32)[None],
                              torch.tensor(g["Th"], dtype=torch.float32)[None], shape=shape)
        joints[frame] = posed.joint_transforms[0, :, :3, 3].numpy().astype(np.float64)
    joints["semantic"] = dict(body.semantic_joints)
    return root, joints
