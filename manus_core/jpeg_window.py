"""A window of a JPEG frame, decoded for a fraction of a whole decode's cost, with the same pixels,
into its place in a frame-sized buffer (so that what crops it maps the frame's pixels as before).

libjpeg-turbo entropy-decodes the rows above the window without transforming them, transforms and
converts only the window's columns (widened to its iMCU grid, 8 or 16 px) and stops after the
window's last row (csrc/jpeg_window.c, built by `make` into _jpeg_window.so and called through
ctypes). A tracked hand's crop at 1280x720 costs 1.5-2.1 ms against a whole frame's 3.9-4.2
(docs/scale.md). Where the library was not built, `available()` is False and callers decode
whole frames.
"""

from __future__ import annotations

import ctypes
from pathlib import Path

import numpy as np

LIBRARY = Path(__file__).with_name("_jpeg_window.so")
_MESSAGE = 256       # libjpeg's messages are at most JMSG_LENGTH_MAX (200) bytes


def _load() -> ctypes.CDLL | None:
    try:
        lib = ctypes.CDLL(str(LIBRARY))
    except OSError:
        return None
    f = lib.mc_decode_window
    f.restype = ctypes.c_int
    count = ctypes.POINTER(ctypes.c_int)
    f.argtypes = [ctypes.c_void_p, ctypes.c_ulong, ctypes.c_int, ctypes.c_int, ctypes.c_int, ctypes.c_int,
                  ctypes.c_void_p, ctypes.c_int, ctypes.c_int, count, count, ctypes.c_char_p, ctypes.c_int]
    return lib


_LIB = _load()


def available() -> bool:
    """Whether the window decoder was built (`make`)."""
    return _LIB is not None


def decode_window(packet: np.ndarray, x: int, y: int, w: int, h: int, out: np.ndarray) -> tuple[int, int]:
    """Rows y .. y+h-1 and at least columns x .. x+w-1 of a JPEG (1-D uint8), BGR, into their place
    in `out` (H,W,3) uint8 C-contiguous, the frame's size. Returns the columns (x', w') that now
    hold the whole decode's pixels, x widened to the iMCU grid; in those rows one column on either
    side of them may be written too, no other pixel of `out` is. ValueError with libjpeg's message
    for a JPEG it cannot decode, a window outside the frame or a buffer of another size."""
    if _LIB is None:
        raise RuntimeError(f"{LIBRARY} is not built (run make)")
    if out.dtype != np.uint8 or out.ndim != 3 or out.shape[2] != 3 or not out.flags.c_contiguous:
        raise ValueError(f"out must be an (H,W,3) C-contiguous uint8 array, not {out.shape} {out.dtype}")
    packet = np.ascontiguousarray(packet, np.uint8)
    got_x, got_w = ctypes.c_int(), ctypes.c_int()
    message = ctypes.create_string_buffer(_MESSAGE)
    status = _LIB.mc_decode_window(packet.ctypes.data, packet.size, int(x), int(y), int(w), int(h),
                                   out.ctypes.data, out.shape[1], out.shape[0], ctypes.byref(got_x),
                                   ctypes.byref(got_w), message, _MESSAGE)
    if status:
        raise ValueError(message.value.decode(errors="replace"))
    return got_x.value, got_w.value
