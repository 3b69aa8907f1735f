"""The `manus-capture` command line.

Commands are loaded on demand: `--help` imports no command module (so neither torch nor pycolmap),
and a command imports only its own module and what that module needs.

Exit codes: 0 success, 1 the work ran and failed (a failing check, a verdict), 2 bad input or
usage (a wrong file, a missing key), 130 interrupted. A full disk or a permission error while
writing is one line naming the path, exit 1.
"""

from __future__ import annotations

import importlib
import sys

import click

from manus_core.errors import ManusError
from manus_core.fileio import as_output_error

from . import __version__

# name -> (module under manus_capture.commands that defines `command`, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "rig": ("rig", "Create, check and list rig configurations (rig.toml)."),
    "leds": ("leds", "Switch, set and flash the LED panels."),
    "record": ("record", "Record a take from every camera of the rig."),
    "recover": ("recover", "Finish a take whose recorder was killed mid-take."),
    "protocol": ("protocol", "Walk through the capture protocol of a session, one take per step."),
    "sync-report": ("sync_report", "Validate the synchronization of a recorded take."),
    "monitor": ("monitor", "Serve the monitor page for a recorded take or session."),
    "calibrate": ("calibrate", "Calibrate one camera (intrinsics) or the whole rig."),
    "models": ("models", "Install and list the hand keypoint models."),
    "detect": ("detect", "Detect 2D hand keypoints in every view of a take."),
    "annotate": ("annotate", "Triangulate, fit the hand skeleton and filter: the dataset file."),
    "stats": ("stats", "Summarize a dataset file: coverage, errors, grip aperture."),
    "segment": ("segment", "Hand and object masks, and the green-paint contact truth."),
    "reconstruct": ("reconstruct", "Train Gaussian models of the object and the hand."),
    "refine": ("refine", "Refine the hand poses of takes against their images through MANUS-Hand."),
    "contacts": ("contacts", "Hand-object contacts from the Gaussian models."),
    "evaluate": ("evaluate", "Score estimated contacts against the paint ground truth."),
    "demo": ("demo", "Run the whole pipeline on the simulated rig and report every stage."),
    "import": ("release_import", "Import a released dataset (MANUS-Grasps, BRICS) as a session."),
    "export": ("release_export", "Export takes in the layouts other tools read (MANUS release, nerfstudio)."),
}


class LazyGroup(click.Group):
    """A group whose sub-commands live in manus_capture.commands.<module>.command."""

    def list_commands(self, ctx: click.Context) -> list[str]:
        return list(COMMANDS)

    def get_command(self, ctx: click.Context, name: str) -> click.Command | None:
        if name not in COMMANDS:
            return None
        module_name, _ = COMMANDS[name]
        return importlib.import_module(f"{__package__}.commands.{module_name}").command

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        # Listing uses the table, so `--help` stays fast and never imports a command module.
        rows = [(name, help_text) for name, (_, help_text) in COMMANDS.items()]
        with formatter.section("Commands"):
            formatter.write_dl(rows)

    def invoke(self, ctx: click.Context):
        try:
            return super().invoke(ctx)
        except (click.ClickException, click.exceptions.Exit, click.exceptions.Abort):
            raise
        except KeyboardInterrupt:
            click.echo("interrupted", err=True)
            ctx.exit(130)
        except (ManusError, OSError, RuntimeError) as exc:
            # Every error raised on purpose carries its exit code, and so does a write that failed
            # for want of space or permission (most outputs already say so in fileio; h5py raises
            # OSError or RuntimeError): one line, not a traceback. Anything else is a bug and keeps
            # its traceback.
            error = exc if isinstance(exc, ManusError) else as_output_error(exc)
            if error is None:
                raise
            err = click.ClickException(str(error))
            err.exit_code = error.exit_code
            raise err from exc


@click.group(cls=LazyGroup, context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(__version__, prog_name="manus-capture")
def cli() -> None:
    """Multi-view hand-object grasp capture: record, calibrate, annotate, reconstruct, score."""


def main() -> None:
    cli(prog_name="manus-capture")


if __name__ == "__main__":
    sys.exit(main())
