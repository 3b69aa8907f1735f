"""Frames as stored: JPEG bytes as the camera sent them, raw pixels encoded on the host."""

from __future__ import annotations

import cv2
import numpy as np

from manus_core.frames_csv import FLAG_HOST_JPEG

from ..cameras import Frame

_BAYER = {"bayer_rg8": "COLOR_BayerRGGB2BGR", "bayer_gr8": "COLOR_BayerGRBG2BGR",
          "bayer_gb8": "COLOR_BayerGBRG2BGR", "bayer_bg8": "COLOR_BayerBGGR2BGR"}
_HIGH_BIT = {"mono10": 2, "mono12": 4, "mono16": 8}   # bits to drop to keep the top 8
_BYTES_PER_PIXEL = {"mono8": 1, **dict.fromkeys(_HIGH_BIT, 2), **dict.fromkeys(_BAYER, 1),
                    "bgr8": 3, "rgb8": 3, "uyvy": 2, "yuyv": 2}


def frame_jpeg(frame: Frame, params: list[int]) -> tuple[bytes, int]:
    """(JPEG bytes, frames.csv flags): JPEG frames as they came; raw pixels encoded with the
    cv2.imencode `params` (StorageConfig.jpeg_params)."""
    if frame.encoding == "jpeg":
        return frame.data, 0
    w, h, enc = frame.width, frame.height, frame.encoding
    if enc not in _BYTES_PER_PIXEL:
        raise ValueError(f"pixel encoding {enc!r} cannot be stored (known: jpeg, {', '.join(_BYTES_PER_PIXEL)})")
    if len(frame.data) < w * h * _BYTES_PER_PIXEL[enc]:
        raise ValueError(f"a {enc} frame of {len(frame.data)} bytes is too short for {w}x{h}")
    buf = np.frombuffer(frame.data, np.uint8)
    if enc == "mono8":
        image = buf[:w * h].reshape(h, w)
    elif enc in _HIGH_BIT:
        image = (np.frombuffer(frame.data, "<u2")[:w * h].reshape(h, w) >> _HIGH_BIT[enc]).astype(np.uint8)
    elif enc in _BAYER:
        image = cv2.cvtColor(buf[:w * h].reshape(h, w), getattr(cv2, _BAYER[enc]))
    elif enc in ("bgr8", "rgb8"):
        image = buf[:w * h * 3].reshape(h, w, 3)
        if enc == "rgb8":
            image = cv2.cvtColor(image, cv2.COLOR_RGB2BGR)
    else:
        code = cv2.COLOR_YUV2BGR_UYVY if enc == "uyvy" else cv2.COLOR_YUV2BGR_YUY2
        image = cv2.cvtColor(buf[:w * h * 2].reshape(h, w, 2), code)
    ok, out = cv2.imencode(".jpg", image, params)
    if not ok:
        raise ValueError(f"JPEG encoding of a {w}x{h} {enc} frame failed")
    return out.tobytes(), FLAG_HOST_JPEG
