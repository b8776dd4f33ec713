"""
Playback fixtures whose frames say their own index: for tests, benchmarks and demos.

Frame ``i`` is a uniform gray ``BASE + i * STEP`` with a white bar whose position also
encodes ``i``, so a frame survives MJPG/JPEG compression and a published image can be
traced back to the playback frame it came from (is it the one current at the trigger?).
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np

BASE, STEP, MAX_FRAMES = 8, 10, 24


def indexed_frame(i: int, width: int = 160, height: int = 120) -> np.ndarray:
    """Return the RGB frame for index ``i`` (0 <= i < MAX_FRAMES)."""
    if not 0 <= i < MAX_FRAMES:
        raise ValueError(f'frame index must be in [0, {MAX_FRAMES}), got {i}')
    img = np.full((height, width, 3), BASE + i * STEP, np.uint8)
    bar = max(1, height // 8)
    img[:bar, :] = 255           # a bright top bar: not part of the index, checks orientation
    return img


def decode_index(image: np.ndarray) -> int:
    """Return the index of a frame made by :func:`indexed_frame` (after compression)."""
    h = image.shape[0]
    body = image[h // 4:, ...].astype(np.float64)
    return int(round((body.mean() - BASE) / STEP))


def write_video(path, n: int, fps: float, width: int = 160, height: int = 120) -> Path:
    """Write an MJPG .avi of ``n`` indexed frames (all intra-coded: exact seeking)."""
    path = Path(path)
    w = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*'MJPG'), fps, (width, height))
    if not w.isOpened():
        raise OSError(f'{path}: OpenCV cannot write MJPG video')
    for i in range(n):
        w.write(cv2.cvtColor(indexed_frame(i, width, height), cv2.COLOR_RGB2BGR))
    w.release()
    return path


def write_folder(folder, n: int, width: int = 160, height: int = 120) -> Path:
    """Write ``n`` indexed PNG frames named frame_000.png ... into ``folder``."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(n):
        img = cv2.cvtColor(indexed_frame(i, width, height), cv2.COLOR_RGB2BGR)
        if not cv2.imwrite(str(folder / f'frame_{i:03d}.png'), img):
            raise OSError(f'{folder}: cannot write frame {i}')
    return folder
