"""hw.FrameGrabber on a real video stream (a file through OpenCV's FFmpeg backend, as a
capture device delivers frames): buffered frames are discarded before each grab, the
region is cropped and grey, and a source that runs dry is one clear error."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calib.errors import FrameGrabberError
from hw.config import GrabberConfig
from hw.grabber import FrameGrabber

LEVELS = [20 + 25 * i for i in range(9)]  # frame i is uniformly this bright


@pytest.fixture
def video(tmp_path):
    path = tmp_path / "scanner.avi"
    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"MJPG"), 30.0, (64, 48))
    assert writer.isOpened()
    for level in LEVELS:
        frame = np.full((48, 64, 3), level, np.uint8)
        frame[:8, :8] = 255  # a bright corner outside the region of interest
        writer.write(frame)
    writer.release()
    return path


def _index(image: np.ndarray) -> int:
    return int(np.argmin([abs(float(np.median(image)) - level) for level in LEVELS]))


def test_buffered_frames_are_discarded_before_each_grab(video):
    cfg = GrabberConfig(source=str(video), flush_frames=2, roi_px=(16, 12, 40, 30), timeout_s=0.3)
    with FrameGrabber(cfg) as grabber:
        first, second = grabber.grab(), grabber.grab()
        assert [_index(first.image), _index(second.image)] == [2, 5]
        assert first.image.shape == (30, 40) and first.image.dtype == np.uint8
        assert first.image.max() < 255  # the corner outside the region is cut away
        assert first.spacing == (1e-4, 1e-4)
        assert _index(grabber.grab().image) == 8
        with pytest.raises(FrameGrabberError, match=r"no frame for 0\.3 s"):
            grabber.grab()  # the stream has run dry


def test_without_flushing_every_frame_comes_in_order(video):
    with FrameGrabber(GrabberConfig(source=str(video), flush_frames=0)) as grabber:
        assert [_index(grabber.grab().image) for _ in range(4)] == [0, 1, 2, 3]


def test_a_region_larger_than_the_frame_is_refused(video):
    grabber = FrameGrabber(GrabberConfig(source=str(video), roi_px=(0, 0, 65, 48)))
    with grabber, pytest.raises(FrameGrabberError, match="outside the captured 64 × 48 frame"):
        grabber.grab()
