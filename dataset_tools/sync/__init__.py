"""Sync validation of a recorded take (DESIGN.md: "The stages", 2, and "sync_report.json").

Per camera: a robust fit of the device clock to the host clock (clock), drops from sequence gaps
and at the ends of a take, duplicate and non-monotonic timestamps (drops), frame-interval
statistics (analysis). Per take: every camera's frames assigned to the rig's nominal ticks
(grouping: the frame groups later stages work on), the real spread of exposure times within each
group, an optical check against LED flashes (optical), whether the take's files are whole
(files: status, videos against frames.csv, unknown cameras), a verdict (report).

Everything but `takes` works on plain arrays; `sync_take` runs it on a take folder
(manus_core.take.Take) and writes TAKE/sync_report.json, .md, .png and the frame groups it
measured (frame_groups.npz, groups_file); `frame_groups(take)` is how annotate, segment and the
reconstruction get a take's groups. docs/sync.md explains the estimator and every number.

Times: ns on the host clock (CLOCK_MONOTONIC) unless a name says otherwise.
"""

from .analysis import SYNC_MODES, CameraSync, SyncResult, SyncSettings, analyze_camera, analyze_sync
from .clock import ClockFit, fit_clock
from .drops import SequenceCheck, check_sequence, end_drops, tick_edge_drops
from .files import TakeFiles, check_files
from .grouping import FrameGroups, group_frames, spread_floor_ns
from .groups_file import GROUPS_FILE, RELEASE_METHOD, TakeGroups, load_groups, save_groups
from .optical import BrightnessFn, Flash, led_flashes, optical_check
from .report import REPORT_VERSION, build_report, noise_range_ns, report_markdown, take_state, timeline_png
from .takes import analyze_take, frame_groups, refuse_overwrite, sync_take, take_brightness, take_flashes

__all__ = ["SYNC_MODES", "CameraSync", "SyncResult", "SyncSettings", "analyze_camera", "analyze_sync", "ClockFit",
           "fit_clock", "SequenceCheck", "check_sequence", "end_drops", "tick_edge_drops", "TakeFiles",
           "check_files", "FrameGroups", "group_frames", "spread_floor_ns",
           "GROUPS_FILE", "RELEASE_METHOD", "TakeGroups", "load_groups", "save_groups", "BrightnessFn", "Flash",
           "led_flashes",
           "optical_check", "REPORT_VERSION", "build_report", "noise_range_ns", "report_markdown", "take_state",
           "timeline_png",
           "analyze_take", "frame_groups", "refuse_overwrite", "sync_take", "take_brightness", "take_flashes"]
