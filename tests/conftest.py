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
