"""The camera backends by name (rig.toml's `backend`): what the recorder opens a rig's cameras
with and what `rig list` asks for the cameras plugged in.

Each backend module describes itself in a `BACKEND` record (rig.cameras.Backend) and is listed
here once; nothing else in the project names a backend. A new backend is one more module and one
more entry; tests put their fakes in with monkeypatch.setitem(BACKENDS, name, backend).
"""

from __future__ import annotations

from .cameras import Backend, aravis, v4l2
from .sim import backend as sim

BACKENDS: dict[str, Backend] = {b.name: b for b in (sim.BACKEND, v4l2.BACKEND, aravis.BACKEND)}
