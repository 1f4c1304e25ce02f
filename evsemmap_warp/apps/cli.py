"""``evsemmap``: a thin command line over the library (flags -> configs -> pipeline calls). Each command
is one module of ``apps/commands`` (its flags in ``add_parser``, its work in ``run``); this one composes
them and answers errors in one line."""

from __future__ import annotations

import argparse
import re
import sys
import warnings

from ..config import ConfigError
from .commands import (args, batch, check_data, demo, dump_config, eval_seg, experiment, export, infer, info, layers, merge, project,
                       synth, train_convbki, train_seg, view)
from .commands import map as map_command  # "map" is a builtin's name

# The commands in the order ``evsemmap --help`` lists them; live and replay (live/commands.py) come after demo.
COMMANDS = (map_command, batch, export, layers, merge, view, train_seg, eval_seg, infer, synth, check_data, project, train_convbki,
            experiment, demo)
LAST_COMMANDS = (info, dump_config)


class _Parser(argparse.ArgumentParser):
    """argparse with the CLI's error form: one line naming the flag and value, exit code 2."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        # argparse takes "-inf" or "-1e3" for a flag; these are numbers (no flag of ours looks like one)
        self._negative_number_matcher = re.compile(r"^-(?:\d+\.?\d*(?:e[-+]?\d+)?|\.\d+(?:e[-+]?\d+)?|inf(?:inity)?|nan)$", re.IGNORECASE)

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The ``evsemmap`` argument parser: one subcommand per task, each with its flags and help."""
    parser = _Parser(prog="evsemmap", description="Evidential semantic mapping on Warp kernels.")
    sub = parser.add_subparsers(dest="command", required=True)
    for command in COMMANDS:
        command.add_parser(sub)
    from ..live.commands import add_parsers as add_live_parsers  # evsemmap live, evsemmap replay (imports no zenoh)

    add_live_parsers(sub, positive=args.positive, positive_float=args.positive_float, port=args.port)
    for command in LAST_COMMANDS:
        command.add_parser(sub)
    return parser


def _warning_line(message, category, filename, lineno, file=None, line=None) -> None:
    # A command's user wants what is wrong in one line, not the source line that noticed it; tqdm.write keeps
    # a progress bar on screen intact.
    from tqdm import tqdm

    tqdm.write(f"evsemmap: warning: {message}", file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    """Run ``evsemmap`` with ``argv`` (default: the process's arguments); returns the exit code. A
    ConfigError, ValueError or OSError ends in one line on stderr naming the file, key or value, with exit
    code 2; Ctrl-C in 130. A warning is one line, ``evsemmap: warning: ...``."""
    args = build_parser().parse_args(argv)
    with warnings.catch_warnings():
        warnings.showwarning = _warning_line
        return _run(args)


def _run(args) -> int:
    try:
        return args.func(args)
    except (ConfigError, ValueError, OSError) as exc:  # OSError: missing or unreadable files, named by the OS
        # One line, even for messages that carry their own line breaks (YAML parser errors).
        text = "; ".join(line.strip() for line in str(exc).splitlines() if line.strip())
        print(f"evsemmap: error: {text}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("evsemmap: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
