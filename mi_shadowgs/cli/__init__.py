"""The ``mi-shadowgs`` command line.

Each subcommand lives in a module of the stage that owns it; this file only lists them.
A command module provides ``add_arguments(parser)`` and ``run(args) -> int``, and keeps its
heavy imports inside ``run`` so that ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import sys

# name -> (module, one-line help)
COMMANDS: dict[str, tuple[str, str]] = {
    "generate": ("mi_shadowgs.cli.generate",
                 "render a shadowed synthetic dataset from a scene XML"),
    "import": ("mi_shadowgs.cli.import_",
               "your own photos (SfM) or a COLMAP model as a dataset, in one world frame"),
    "render": ("mi_shadowgs.cli.render", "render a surfel model (PLY) from dataset cameras"),
    "segment": ("mi_shadowgs.cli.segment",
                "material segments: contrastive surfel features + K-means (stage 2)"),
    "train": ("mi_shadowgs.cli.train", "optimise a stage of the method on a dataset (geometry)"),
    "run": ("mi_shadowgs.cli.run", "the whole method on a dataset (stages 1-5) and its report"),
    "report": ("mi_shadowgs.cli.report", "write the HTML report of a run"),
    "relight": ("mi_shadowgs.cli.relight",
                "render a finished run's model under new lights (directional, env map, scene)"),
    "view": ("mi_shadowgs.cli.view",
             "a run in the browser: move the light, see the shadows move (local web viewer)"),
    "export": ("mi_shadowgs.cli.export",
               "a run's model as a 3DGS/2DGS PLY or a mesh with materials and a Mitsuba scene"),
    "batch": ("mi_shadowgs.cli.batch",
              "many captures (import + run each) as Ray tasks, here or on a cluster"),
}


class CLIError(Exception):
    """A user-facing error: printed as one line, exit status 2."""


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mi-shadowgs",
        description="Shadow-aware inverse rendering with 2D Gaussian surfels (Mitsuba 3).",
    )
    parser.add_argument("--variant", default=None,
                        help="Mitsuba variant: llvm_ad_rgb (default) or cuda_ad_rgb")
    parser.add_argument("--threads", type=int, default=None, metavar="N",
                        help="Dr.Jit's CPU threads (default: every core); with one, a "
                             "command's outputs are the same bytes every time")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, (module, help_text) in COMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        p.set_defaults(_module=module)
        importlib.import_module(module).add_arguments(p)
    return parser


# What an interrupted command says about continuing (default: run it again).
RESUME_HINTS = {"train": "run it again with --resume to continue",
                "segment": "run it again with --resume to continue"}
# Commands whose --overwrite would remove the views an interrupted call wrote: the same
# command again would start over, so the hint drops the flag.
OVERWRITE_RESTARTS = ("render", "relight")
# Commands that serve until stopped: a signal is how they end, with nothing to continue.
STOPPED_BY_SIGNAL = ("view",)


# The argument that names each command's output folder (locked while it runs); commands
# that write nothing are absent.
OUTPUT_ARGUMENT = {"generate": "out", "import": "out", "render": "out", "segment": "out",
                   "train": "out", "run": "out", "report": "run", "relight": "out",
                   "export": "out", "batch": "out"}
# Commands whose work runs in other processes: --variant is theirs, not this process's.
DELEGATES_BACKEND = ("batch",)


def _note(line: str) -> None:
    print(f"mi-shadowgs: note: {line}", file=sys.stderr, flush=True)


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    from mi_shadowgs import backend
    from mi_shadowgs.io.interrupt import Interrupted, handle_signals
    from mi_shadowgs.io.outlock import describe_os_error, output_lock

    folder = getattr(args, OUTPUT_ARGUMENT.get(args.command, ""), None)
    hint = RESUME_HINTS.get(args.command, "run the same command again to continue")
    try:
        with contextlib.ExitStack() as stack:
            if folder is not None:  # before anything is read: a second writer stops at once
                stack.enter_context(output_lock(folder, args.command, note=_note))
            stack.enter_context(handle_signals())
            if args.threads is not None:
                if args.threads < 1:
                    raise CLIError(f"--threads must be >= 1, got {args.threads}")
                import drjit as dr

                dr.set_thread_count(args.threads)
            if args.command not in DELEGATES_BACKEND:
                backend.set_variant(args.variant)
            return int(importlib.import_module(args._module).run(args) or 0)
    except (CLIError, backend.BackendError, FileNotFoundError, FileExistsError,
            ValueError) as exc:
        print(f"mi-shadowgs {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except (PermissionError, IsADirectoryError, NotADirectoryError) as exc:
        # A path given (or one under it) that this user may not use, or a folder where a
        # file should be: the OS names it. Without a path it is no user's input: traceback.
        if exc.filename is None:
            raise
        print(f"mi-shadowgs {args.command}: error: {exc.filename}: {exc.strerror}",
              file=sys.stderr)
        return 2
    except OSError as exc:
        # Read-only, full, over quota, a name too long: the output path's fault, named.
        line = describe_os_error(exc, folder, hint)
        if line is None:
            raise
        print(f"mi-shadowgs {args.command}: error: {line}", file=sys.stderr)
        return 2
    except Interrupted as exc:
        if args.command in STOPPED_BY_SIGNAL:
            print(f"mi-shadowgs {args.command}: stopped", flush=True)
            return 0
        if args.command in OVERWRITE_RESTARTS and args.overwrite:
            hint = "run it again without --overwrite to continue"
        print(f"mi-shadowgs {args.command}: interrupted by {exc}; {hint}", file=sys.stderr)
        return exc.exit_code
