"""`python -m app review RUN.rrd [--json FILE] [--plots DIR] [--viewer]`: summary and plots of a race
recording (simulated `race` or the real-time loop); docs/race-stack.md."""
from __future__ import annotations

import json
import subprocess
from pathlib import Path

from app.cli import UserError
from app.live_view import display_problem, viewer_executable
from fileio import atomic_write_text, check_output_path
from race.recording import RecordingError, load_recording
from race.review import format_summary, save_plots, summarize


def register(sub) -> None:
    p = sub.add_parser("review", help="summarise a race recording (.rrd): laps, gaps, timing, tracking; plots")
    p.add_argument("recording", help="rerun recording written by `python -m app race`")
    p.add_argument("--json", help="write the summary as JSON here")
    p.add_argument("--plots", help="folder for the PNG plots (default: RUN_review/ next to the recording)")
    p.add_argument("--no-plots", action="store_true", help="do not write plots")
    p.add_argument("--viewer", action="store_true", help="also open the recording in the Rerun viewer")
    p.set_defaults(func=run)


def viewer_command(path: Path) -> list[str]:
    """The command that opens the recording in the Rerun viewer; UserError if none can be shown."""
    exe = viewer_executable("--viewer", f"install rerun-sdk and run `rerun {path}`")
    problem = display_problem()
    if problem:
        raise UserError(f"--viewer: {problem}; copy {path} to a machine with a display and run `rerun {path}`")
    return [exe, str(path)]


def run(args) -> int:
    path = Path(args.recording)
    try:
        data = load_recording(path)
    except RecordingError as exc:
        raise UserError(str(exc)) from None
    summary = summarize(data)
    print(format_summary(summary, data))
    if args.json:
        check_output_path(args.json, stream=True)
    folder = Path(args.plots) if args.plots else path.with_name(path.stem + "_review")
    if not args.no_plots and folder.exists() and not folder.is_dir():
        raise UserError(f"--plots: {folder} is a file, not a folder for the plots")
    if not args.no_plots:
        written = save_plots(data, folder)
        print("plots: " + ", ".join(str(p) for p in written))
    if args.json:
        atomic_write_text(args.json, json.dumps(summary, indent=2) + "\n", stream=True)
        print(f"summary: {args.json}")
    if args.viewer:
        cmd = viewer_command(path)
        try:
            subprocess.Popen(cmd, start_new_session=True)
        except OSError as exc:
            raise UserError(f"--viewer: cannot start {cmd[0]}: {exc}") from None
        print(f"viewer: {' '.join(cmd)}")
    return 0
