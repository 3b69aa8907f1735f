"""The live web monitor of a recording, and the same page over recorded takes (docs/recording.md,
"The monitor").

Starlette on uvicorn: an ASGI server that streams server-sent events, runs in a thread of the
recording process with its own event loop, and comes with a test client. `start_monitor` serves a
`MonitorSource` (the recorder, or a `RecordedSource` over a take or session folder).
"""

from .app import build_app
from .recorded import RecordedSource, RecordedTake
from .server import DEFAULT_HOST, DEFAULT_PORT, MonitorServer, parse_address, start_monitor
from .source import MonitorSource

__all__ = ["build_app", "RecordedSource", "RecordedTake", "DEFAULT_HOST", "DEFAULT_PORT", "MonitorServer",
           "parse_address", "start_monitor", "MonitorSource"]
