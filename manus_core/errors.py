"""Every error of manus-capture, and the exit code the CLI gives it.

ManusError is the one base: the CLI turns any ManusError into one line on stderr and exits with
its `exit_code` (2: bad input or usage, naming the file and the problem; 1: the work ran and
failed, or a device failed). Anything else is a bug and keeps its traceback.
"""

from __future__ import annotations


class ManusError(Exception):
    """The base of every error the toolkit raises on purpose."""

    exit_code = 1


class InputError(ManusError, ValueError):
    """Bad input: a file, a value or an option that cannot be used; names it and the problem."""

    exit_code = 2


class DeviceError(ManusError, RuntimeError):
    """A device (camera, LED controller) that failed while in use."""

    exit_code = 1


class DemoError(ManusError):
    """A demo stage failed (exit code 1): the message names the stage."""


class EvaluateError(InputError):
    """Evaluation cannot run on the given input (exit code 2)."""


class BuildError(InputError):
    """The takes cannot give a model (exit code 2)."""


class CheckpointError(InputError):
    """A file that is not a readable manus-capture splat checkpoint."""


class LPIPSWeightsError(InputError):
    """LPIPS was asked for and its pretrained weights are not installed."""


class TakeInputError(InputError):
    """A take, ground truth or dataset that cannot give training views; names the file (exit code 2)."""


class OutputExists(InputError, FileExistsError):
    """An output file is already there and overwriting was not asked for (--force)."""


class ReconstructInputError(InputError):
    """Bad input to reconstruct: names the file and the problem (exit code 2)."""


class NoLedsError(InputError):
    """The rig has no LED controller configured."""


class RecordError(InputError):
    """A take that cannot be recorded as asked (exists, bad options, no disk); names the path."""


class DiskSpaceError(RecordError):
    """Less free disk than the take needs."""


class CameraError(DeviceError):
    """A camera that cannot be opened, configured or read; names the camera."""


class CameraDisconnected(CameraError):
    """The camera went away mid-stream; frames already read stay valid."""


class LedError(DeviceError):
    """The LED controller failed (no answer, gone, or refused a command); names the port."""


class LedTimeout(LedError):
    """The controller did not answer a command within its retries."""


class LedDisconnected(LedError):
    """The port went away and did not come back within the reconnect budget."""


class LedRejected(LedError):
    """The controller answered ERR."""


class LedValueError(InputError):
    """A level, panel or duration out of range (bad input, exit code 2)."""


class LinkLost(ManusError, OSError):
    """Internal: the serial port failed mid-exchange; the controller reconnects."""


class SyncError(InputError):
    """Input the sync stage cannot work with; names the file and the problem (exit code 2)."""


class SyncReportExists(SyncError, FileExistsError):
    """A sync report is already there and overwriting was not asked for."""


class AnnotateError(InputError):
    """Bad input to annotate (calibration, cameras, keypoints, takes); names the file and the problem."""


class SimulatedDetectorError(InputError):
    """Inputs the simulated detector cannot use (shapes, ground truth, cameras)."""


class GroundTruthError(InputError):
    """A ground_truth.h5 that is missing, unreadable or lacks what was asked of it; names the file."""


class OneEuroError(InputError):
    """Bad input to the filter (shapes, timestamps, parameters); the message says which."""


class TriangulationError(InputError):
    """Inputs that cannot be triangulated as given (shapes, camera ids, parameters)."""


class SegmentationError(InputError):
    """Input that segmentation cannot work with; the message names the input and the problem."""


class BoneLengthError(InputError):
    """Bone lengths that cannot be estimated or a subject file that cannot be read."""


class IKError(InputError):
    """Inputs that cannot be fitted as given (shapes, weights, initial angles)."""


class ModelError(InputError):
    """A model that is missing, corrupt or does not fit; names the file and the problem."""


class ModelNotInstalledError(ModelError):
    """A model that is not in the cache: the message names the install command."""


class InstallError(ManusError, RuntimeError):
    """`models install` could not finish (no network, a failed conversion or check)."""

    exit_code = 2


class CalibrationError(InputError):
    """Input the calibration cannot use; the message names the cameras (or the file and key)."""


class BoardError(CalibrationError):
    """A board or tag layout file that cannot be used; the message names the file and the key."""


class DetectionError(CalibrationError):
    """Input images that cannot be used (unreadable, mixed sizes, no target found)."""


class IntrinsicsError(CalibrationError):
    """Too little or unusable data for an intrinsic calibration; names the camera."""

    def __init__(self, camera: str, reason: str) -> None:
        super().__init__(f"camera {camera}: {reason}")
        self.camera, self.reason = camera, reason


class ExtrinsicsError(CalibrationError):
    """Cameras that cannot be placed; the message names them and says why."""


class UnplacedCamerasError(ExtrinsicsError):
    """Cameras the calibration ran on but could not place, from their tags nor from the scene
    (exit code 1: the work ran and failed); the message names them and says why."""

    exit_code = 1


class ColmapError(CalibrationError):
    """COLMAP could not register the cameras, or the result cannot be put into the world frame."""


class SchedulerError(InputError):
    """A Dask scheduler address that does not answer; the message names it."""


class DatasetError(InputError):
    """A dataset file that cannot be read or written as asked; names the file."""


class CalibrationFileError(InputError):
    """A calibration file that cannot be read; names the file and the problem."""


class ConfigError(InputError):
    """A configuration problem, worded as 'FILE: KEY: what is wrong'."""


class SessionError(InputError):
    """A session folder or session.toml that does not fit the request; names the file."""


class TakeError(InputError):
    """A take folder or one of its files that cannot be read; names the file and the problem."""


class OutputError(ManusError, OSError):
    """An output that could not be written (disk full, no permission, read-only); names the path.

    Also an OSError with the errno of the failed write, so code that handles a full disk itself
    (the recorder) still recognizes it."""

    exit_code = 1


class LedStaleReply(LedError):
    """The controller answered a request with a reply that cannot be its own (one it kept for an
    earlier request with the same number): the command was not carried out."""


class MonitorError(InputError):
    """The monitor cannot serve as asked (an address in use, a bad address or token, a folder
    that is no take or session); names the address or folder (exit code 2)."""


class ReleaseError(InputError):
    """A MANUS/BRICS release folder (or an export into that layout) that cannot be read or
    written as asked; names the file or folder and what was looked for."""


class RefineInputError(InputError):
    """Pose refinement cannot run on the given input: names the files and the problem (exit code 2)."""
