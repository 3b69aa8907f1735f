"""Recording takes (stage 1): every camera of a rig into one take folder.

    from rig.record import RecordOptions, record_take
    result = record_take(rig, "s01", "grasp1", "grasp", 5.0, RecordOptions(flash_ms=50))

record_take (rig.record.take) checks the take, opens the cameras through their backends and
keeps session.toml; Recorder (rig.record.recorder) records any Camera objects on one clock;
its pieces: streams (reader and writer threads, frames.csv), jpeg (frames as stored),
led_plan (LED commands on the take's clock), disk (space checks), stop (why a take ends),
report (what it delivered), recover (finishing a take whose recorder was killed), live (the take
and the session as a monitor reads them while they record).
"""

from __future__ import annotations

from .jpeg import FLAG_HOST_JPEG
from .led_plan import flash_offsets
from .live import Live, LiveSession
from .options import RecordOptions
from .recorder import Recorder
from .recover import Recovered, killed, recover_take
from .report import CameraReport, TakeResult
from .stop import StopFlag
from .take import record_take

__all__ = ["FLAG_HOST_JPEG", "CameraReport", "Live", "LiveSession", "RecordOptions", "Recorder", "Recovered",
           "StopFlag", "TakeResult", "flash_offsets", "killed", "record_take", "recover_take"]
