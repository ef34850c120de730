"""A frame's scan file read ahead on the reader thread (:func:`uvatar.avh.bake.inputs.prefetch_scan`)
and taken by :func:`~uvatar.avh.bake.inputs.prepared_scan`: the same scan as a direct read, its error
raised where the direct read would raise it, nothing read ahead for a kept scan or a missing file,
reads dropped with the cache."""

from __future__ import annotations

import threading

import numpy as np
import pytest
from test_avh_bake_helpers import make_capture

from uvatar.avh.bake import inputs
from uvatar.avh.bake.config import BakeConfig
from uvatar.capture import Capture


@pytest.fixture()
def capture(tmp_path, monkeypatch):
    cap = Capture(make_capture(tmp_path / "cap", n_frames=3, broken=(), unreadable=(2,)))
    reads = []
    load = Capture.load_scan

    def counted(self, frame):
        reads.append((frame, threading.current_thread().name))
        return load(self, frame)

    monkeypatch.setattr(Capture, "load_scan", counted)
    monkeypatch.setattr(inputs, "READ_AHEAD_ON_CPU", True)          # as on CUDA
    inputs.clear_scan_cache()
    yield cap, reads
    inputs.clear_scan_cache()


def test_a_read_ahead_is_taken_and_equals_a_direct_read(capture):
    cap, reads = capture
    config = BakeConfig(texels=32)
    inputs.prefetch_scan(cap, "000001", config, run="a")
    inputs.prefetch_scan(cap, "000001", config, run="a")            # already being read: not twice
    scan, surface = inputs.prepared_scan(cap, "000001", config, run="a")
    assert [f for f, _ in reads] == ["000001"] and reads[0][1].startswith("scan-read")
    direct = cap.load_scan("000001")
    for name in ("vertices", "faces", "uvs", "uv_faces", "texture"):
        np.testing.assert_array_equal(getattr(scan, name), getattr(direct, name))
    assert len(surface.faces) == len(direct.faces)
    reads.clear()
    inputs.prefetch_scan(cap, "000001", config, run="a")            # kept: nothing to read
    assert inputs.prepared_scan(cap, "000001", config, run="a")[0] is scan and reads == []


def test_a_broken_scan_read_ahead_raises_where_the_direct_read_does(capture):
    cap, _ = capture
    config = BakeConfig(texels=32)
    with pytest.raises(Exception) as direct:
        inputs.prepared_scan(cap, "000002", config, run="b")
    inputs.clear_scan_cache()
    inputs.prefetch_scan(cap, "000002", config, run="b")
    with pytest.raises(type(direct.value), match="000002"):
        inputs.prepared_scan(cap, "000002", config, run="b")


def test_nothing_is_read_ahead_for_a_missing_file_and_reads_go_with_the_cache(capture):
    cap, reads = capture
    config = BakeConfig(texels=32)
    cap.scan_path("000000").unlink()
    inputs.prefetch_scan(cap, "000000", config, run="c")
    assert not inputs._READING
    inputs.prefetch_scan(cap, "000001", config, run="c")
    assert len(inputs._READING) == 1
    inputs.clear_scan_cache()
    assert not inputs._READING
    inputs.prefetch_scan(cap, "000001", config, run="c")
    inputs.prefetch_scan(cap, "000001", config, run="d")            # a new bake drops the last one's reads
    assert len(inputs._READING) == 1


def test_the_cpu_reads_no_scan_ahead_by_default(capture, monkeypatch):
    cap, reads = capture
    monkeypatch.setattr(inputs, "READ_AHEAD_ON_CPU", False)
    inputs.prefetch_scan(cap, "000001", BakeConfig(texels=32), run="e")
    assert not inputs._READING and reads == []
    monkeypatch.setattr(inputs, "READ_AHEAD_ON_CPU", True)
    monkeypatch.setattr(inputs, "READ_AHEAD", False)                # the benches' way without
    inputs.prefetch_scan(cap, "000001", BakeConfig(texels=32), run="e")
    assert not inputs._READING


def test_a_task_read_ahead_never_raises(tmp_path):
    inputs.prefetch_task_scans({"capture_root": str(tmp_path / "nowhere"), "config": BakeConfig(device="cuda")},
                               ["000000"])
    inputs.prefetch_task_scans({}, ["000000"])                       # not even without its inputs
