"""Command-line interface: ``spectral-fit <command> ...``.

Each subcommand lives in ``spectral_fit/cli/commands/<name>.py`` and defines ``HELP`` (one line),
``add_arguments(parser)`` and ``run(args) -> int``. Command modules import heavy libraries
inside ``run`` so that ``spectral-fit --help`` is quick.
"""

from __future__ import annotations

import argparse
import importlib
import sys
import time

from .._runtime.errors import SpectralFitError

#: ``time.perf_counter()`` when the command-line interface was imported (the command's start,
#: for the timings that commands report)
STARTED = time.perf_counter()

#: subcommand name -> module under spectral_fit.cli.commands
COMMANDS: dict[str, str] = {
    "demo": "demo",
    "bench": "bench",
    "make-env": "make_env",
    "view": "view",
    "render": "render",
    "calibrate": "calibrate",
    "validate": "validate",
    "fit": "fit",
    "plan": "plan",
    "live": "live",
    "calibrate-colour": "calibrate_colour",
    "mr-score": "mr_score",
}


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="spectral-fit",
        description="Differentiable spectral renderer: fit plastic reflection models and render "
        "mixed-reality frames.",
    )
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, module_name in COMMANDS.items():
        module = importlib.import_module(f".commands.{module_name}", __package__)
        p = sub.add_parser(name, help=module.HELP, description=module.HELP)
        module.add_arguments(p)
        p.set_defaults(_run=module.run, _fast_exit=getattr(module, "FAST_EXIT", False))
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the ``spectral-fit`` console script."""
    if argv is None:  # run as a program (not called from Python): steady frame memory
        from .._runtime.process import retain_freed_memory

        retain_freed_memory()
    args = build_parser().parse_args(argv)
    try:
        rc = int(args._run(args) or 0)
    except SpectralFitError as exc:
        print(f"spectral-fit {args.command}: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print(f"spectral-fit {args.command}: interrupted", file=sys.stderr)
        return 130
    if argv is None and args._fast_exit:
        _exit_now(rc)
    return rc


def _exit_now(rc: int) -> None:
    """End the process without the interpreter's teardown, for commands that declare
    ``FAST_EXIT`` (their files are written and synced before they return): unloading JAX and
    XLA at exit takes about half a second. Standard streams and logging are flushed first."""
    import logging
    import os

    logging.shutdown()
    for stream in (sys.stdout, sys.stderr):
        try:
            stream.flush()
        except Exception:  # a closed or broken stream: nothing left to flush
            pass
    os._exit(rc)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
