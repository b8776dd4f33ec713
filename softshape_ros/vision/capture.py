"""
Camera frame sources through OpenCV: a live device, a video file, or a folder of images.

The camera_trigger node asks a source for the frame that is current *now* (right after a
trigger arrived) and never for a buffered one: a live device is grabbed continuously in a
thread and a request is answered by the first grab that completes after it; file and folder
playback is locked to the wall clock (frame ``floor(t * fps) mod N``), so two processes
playing the same file show the same frame at the same instant, as two cameras would.
No rclpy here: the node is a thin adapter.
"""

from __future__ import annotations

import os
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

__all__ = ['CaptureError', 'Frame', 'FrameSource', 'DeviceSource', 'VideoFileSource',
           'ImageFolderSource', 'open_source', 'IMAGE_SUFFIXES']

IMAGE_SUFFIXES = ('.png', '.jpg', '.jpeg', '.bmp', '.tif', '.tiff', '.ppm', '.pgm')


class CaptureError(RuntimeError):
    """The camera cannot give a frame (missing, vanished, unreadable); the message says why."""


@dataclass(frozen=True)
class Frame:
    """One captured frame: RGB uint8 H x W x 3 and when it was captured (time.time_ns())."""

    image: np.ndarray
    capture_ns: int
    index: int = -1          # playback frame index (files, folders); -1 for live devices


def _to_rgb(bgr: np.ndarray) -> np.ndarray:
    if bgr.ndim == 2:
        return cv2.cvtColor(bgr, cv2.COLOR_GRAY2RGB)
    if bgr.ndim == 3 and bgr.shape[2] == 4:
        return cv2.cvtColor(bgr, cv2.COLOR_BGRA2RGB)
    return cv2.cvtColor(bgr, cv2.COLOR_BGR2RGB)


class FrameSource:
    """The interface: ``capture(timeout_s)`` returns the freshest :class:`Frame` or raises."""

    description = 'source'

    def capture(self, timeout_s: float = 1.0) -> Frame:  # pragma: no cover - interface
        raise NotImplementedError

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


class _PlaybackClock:
    """Wall-clock-locked playback: the frame shown at ``t`` is ``floor(t * fps) mod n``."""

    def __init__(self, fps: float, n: int):
        if not fps > 0:
            raise CaptureError(f'playback fps must be > 0, got {fps}')
        self.fps, self.n = float(fps), int(n)

    def index_at(self, t_ns: int) -> int:
        return int((t_ns * self.fps) // 1_000_000_000) % self.n


class ImageFolderSource(FrameSource):
    """Play a folder of images (sorted by name) at ``fps``; each capture re-reads the file."""

    def __init__(self, folder, fps: float = 10.0):
        self.folder = Path(folder)
        self.description = f'folder {self.folder}'
        self.files = self._list()
        self.clock = _PlaybackClock(fps, len(self.files))

    def _list(self) -> list[Path]:
        if not self.folder.is_dir():
            raise CaptureError(f'{self.folder}: image folder does not exist')
        files = sorted(p for p in self.folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
        if not files:
            raise CaptureError(f'{self.folder}: no images ({", ".join(IMAGE_SUFFIXES)})')
        return files

    def capture(self, timeout_s: float = 1.0) -> Frame:
        t = time.time_ns()
        i = self.clock.index_at(t)
        path = self.files[i]
        img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
        if img is None:
            raise CaptureError(f'{path}: cannot read image (missing or corrupt)')
        if img.dtype != np.uint8:
            img = cv2.convertScaleAbs(img, alpha=255.0 / max(1.0, float(img.max())))
        return Frame(_to_rgb(img), t, i)


class VideoFileSource(FrameSource):
    """
    Play a video file at its own fps (or ``fps``), looping, locked to the wall clock.

    Decoding is sequential (``grab`` skips without decoding, ``retrieve`` decodes only the
    frame asked for); going backwards (the loop wrapped) rewinds the file.
    """

    def __init__(self, path, fps: float = 0.0):
        self.path = Path(path)
        self.description = f'video {self.path}'
        if not self.path.is_file():
            raise CaptureError(f'{self.path}: video file does not exist')
        self.cap = self._open()
        n = int(self.cap.get(cv2.CAP_PROP_FRAME_COUNT))
        if n <= 0:
            n = self._count_frames()
        if n <= 0:
            self.cap.release()
            raise CaptureError(f'{self.path}: video has no frames')
        file_fps = float(self.cap.get(cv2.CAP_PROP_FPS) or 0.0)
        self.clock = _PlaybackClock(fps if fps > 0 else (file_fps or 10.0), n)
        self.pos = 0                              # index of the next frame grab() returns

    def _open(self):
        cap = cv2.VideoCapture(str(self.path))
        if not cap.isOpened():
            cap.release()
            raise CaptureError(f'{self.path}: OpenCV cannot open this video')
        return cap

    def _count_frames(self) -> int:
        n = 0
        while self.cap.grab():
            n += 1
        self.cap.release()
        self.cap = self._open()
        return n

    def capture(self, timeout_s: float = 1.0) -> Frame:
        if self.cap is None:
            raise CaptureError(f'{self.path}: closed')
        if not self.path.is_file():               # an open handle outlives the file: check
            raise CaptureError(f'{self.path}: video file vanished')
        t = time.time_ns()
        i = self.clock.index_at(t)
        if i < self.pos:                          # looped: rewind
            if not self.cap.set(cv2.CAP_PROP_POS_FRAMES, 0):
                self.cap.release()
                self.cap = self._open()
            self.pos = 0
        while self.pos < i:
            if not self.cap.grab():
                raise CaptureError(f'{self.path}: video ended early at frame {self.pos}')
            self.pos += 1
        ok, img = self.cap.read()
        if not ok or img is None:
            raise CaptureError(f'{self.path}: cannot decode frame {i}')
        self.pos += 1
        return Frame(_to_rgb(img), t, i)

    def close(self) -> None:
        if self.cap is not None:
            self.cap.release()
            self.cap = None


class DeviceSource(FrameSource):
    """
    A live camera (V4L2 index or ``/dev/video*`` path), grabbed continuously in a thread.

    A capture request is answered by the first ``grab()`` that *starts* after the request,
    then ``retrieve()`` decodes that frame only: the driver's buffer never serves a stale
    frame. A grab failure marks the source dead; the caller closes it and reopens later.
    """

    def __init__(self, device, width: int = 0, height: int = 0, fps: float = 0.0,
                 pixel_format: str = '', api: int = cv2.CAP_V4L2, opener=None):
        self.device = device
        self.description = f'device {device}'
        self._opener = opener or (lambda d: cv2.VideoCapture(d, api))
        self.cap = self._opener(device)
        if self.cap is None or not self.cap.isOpened():
            if self.cap is not None:
                self.cap.release()
            raise CaptureError(f'camera {device}: cannot open (not connected, busy or '
                               'no permission)')
        if pixel_format:
            if len(pixel_format) != 4:
                self.cap.release()
                raise CaptureError(f'pixel_format must be a FOURCC such as MJPG, '
                                   f'got {pixel_format!r}')
            self.cap.set(cv2.CAP_PROP_FOURCC, cv2.VideoWriter_fourcc(*pixel_format))
        if width > 0 and height > 0:
            self.cap.set(cv2.CAP_PROP_FRAME_WIDTH, width)
            self.cap.set(cv2.CAP_PROP_FRAME_HEIGHT, height)
        if fps > 0:
            self.cap.set(cv2.CAP_PROP_FPS, fps)
        self.cap.set(cv2.CAP_PROP_BUFFERSIZE, 1)
        self._cond = threading.Condition()
        self._requests: list[list] = []     # [request_ns, Frame | None, error | None]
        self._error: str | None = None
        self._stop = False
        self._thread = threading.Thread(target=self._run, name=f'grab-{device}', daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop:
            start = time.time_ns()
            ok = self.cap.grab()
            t = time.time_ns()
            with self._cond:
                if not ok:
                    self._error = f'camera {self.device}: grab failed (disconnected?)'
                    for r in self._requests:
                        r[2] = self._error
                    self._requests.clear()
                    self._cond.notify_all()
                    return
                due = [r for r in self._requests if r[0] <= start]
                if due:
                    ok, img = self.cap.retrieve()
                    for r in due:
                        if ok and img is not None:
                            r[1] = Frame(_to_rgb(img), t)
                        else:
                            r[2] = f'camera {self.device}: cannot decode the frame'
                        self._requests.remove(r)
                    self._cond.notify_all()

    def capture(self, timeout_s: float = 1.0) -> Frame:
        req = [time.time_ns(), None, None]
        with self._cond:
            if self._error:
                raise CaptureError(self._error)
            self._requests.append(req)
            ok = self._cond.wait_for(lambda: req[1] is not None or req[2] is not None,
                                     timeout=timeout_s)
            if not ok:
                if req in self._requests:
                    self._requests.remove(req)
                raise CaptureError(f'camera {self.device}: no frame within {timeout_s:.2f} s')
        if req[2]:
            raise CaptureError(req[2])
        return req[1]

    def close(self) -> None:
        self._stop = True
        if self._thread.is_alive():
            self._thread.join(timeout=2.0)
        self.cap.release()


def open_source(spec: str, width: int = 0, height: int = 0, fps: float = 0.0,
                pixel_format: str = '') -> FrameSource:
    """
    Open a source from one string: ``0`` / ``/dev/video0`` (device), a video file, a folder.

    ``fps`` is the device rate for a camera and the playback rate for files and folders
    (0 = the video's own rate; folders default to 10).
    """
    spec = str(spec).strip()
    if not spec:
        raise CaptureError('no camera source given (a device index, /dev/video*, a video file '
                           'or an image folder)')
    if spec.isdigit():
        return DeviceSource(int(spec), width, height, fps, pixel_format)
    if spec.startswith('/dev/'):
        if not os.path.exists(spec):
            raise CaptureError(f'camera {spec}: no such device')
        return DeviceSource(spec, width, height, fps, pixel_format)
    p = Path(spec).expanduser()
    if p.is_dir():
        return ImageFolderSource(p, fps if fps > 0 else 10.0)
    if p.is_file():
        return VideoFileSource(p, fps)
    raise CaptureError(f'{spec}: no such camera device, video file or image folder')
