"""Thumbnails: a camera's JPEG decoded at reduced size and re-encoded small, once per frame.

The decode happens in the server's request threads, never on a recorder's path: the source hands
over the JPEG bytes its writer already has. libjpeg decodes at 1/4 size from the DCT coefficients
(cv2.IMREAD_REDUCED_COLOR_4), several times cheaper than a full decode. Each camera keeps its last
(source bytes, thumbnail) pair, and a lock per camera makes many pollers of a new frame cost one
decode: the others wait for it and get the cached result.

Decoding is also held to a CPU budget (BUDGET of one core over all cameras): a camera whose
last thumbnail is still fresh by that budget gets it again rather than a new decode. At 53 cameras
x 4 polls a second a 720p thumbnail each would take about 0.9 of a core, which a recording
2-core machine does not have to spare; with the budget the page shows each camera a little
less often and the recorder keeps its frames.
"""

from __future__ import annotations

import threading
import time

import cv2
import numpy as np

MAX_WIDTH = 320       # px; a 1/4-size decode wider than this is scaled down further
QUALITY = 70
BUDGET = 0.25         # share of one core that thumbnails may take, over all cameras


def thumbnail(jpeg: bytes) -> bytes | None:
    """A small JPEG of `jpeg`, or None when it cannot be decoded."""
    image = cv2.imdecode(np.frombuffer(jpeg, np.uint8), cv2.IMREAD_REDUCED_COLOR_4)
    if image is None:
        return None
    height, width = image.shape[:2]
    if width > MAX_WIDTH:
        image = cv2.resize(image, (MAX_WIDTH, max(1, round(height * MAX_WIDTH / width))),
                           interpolation=cv2.INTER_AREA)
    ok, out = cv2.imencode(".jpg", image, [cv2.IMWRITE_JPEG_QUALITY, QUALITY])
    return out.tobytes() if ok else None


class Thumbnails:
    """The thumbnail of each camera's latest frame, made once per frame whatever the pollers."""

    def __init__(self, budget: float | None = BUDGET) -> None:
        self._locks: dict[object, threading.Lock] = {}
        self._cache: dict[object, tuple[bytes, bytes | None]] = {}
        self._guard = threading.Lock()
        self.budget = budget
        self._cost_s = 0.0          # seconds of the latest decode
        self._made: dict[object, float] = {}   # when each key's thumbnail was made
        self.decodes = 0   # how many frames were decoded (the cache is measured by it)

    def _fresh(self, key: object, now: float) -> bool:
        """Whether `key`'s thumbnail is recent enough that a new decode would exceed the budget:
        with N cameras each may be decoded once per N x cost / budget seconds."""
        made = self._made.get(key)
        if self.budget is None or made is None:
            return False
        return now - made < len(self._made) * self._cost_s / self.budget

    def get(self, key: object, jpeg: bytes) -> bytes | None:
        """The thumbnail of `jpeg`, the frame now shown for `key` (a camera, or a recorded take's camera)."""
        with self._guard:
            lock = self._locks.setdefault(key, threading.Lock())
        with lock:
            cached = self._cache.get(key)
            # `is` first: a source hands out the same bytes object until its next frame
            if cached is not None and (cached[0] is jpeg or cached[0] == jpeg):
                return cached[1]
            start = time.perf_counter()
            if cached is not None and cached[1] is not None and self._fresh(key, start):
                return cached[1]
            thumb = thumbnail(jpeg)
            done = time.perf_counter()
            self._cost_s, self._made[key] = done - start, done
            self.decodes += 1
            self._cache[key] = (jpeg, thumb)
            return thumb
