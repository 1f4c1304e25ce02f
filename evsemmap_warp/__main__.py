"""``evsemmap`` and ``python -m evsemmap_warp``: the command line, answering Ctrl-C in one line from its first
moment. The command line's own imports (Warp, torch, numpy) take a second or more; an interrupt while they
load would otherwise end in an ImportError's traceback."""

import sys


def main() -> int:
    try:
        from .apps.cli import main as run
    except KeyboardInterrupt:
        print("evsemmap: interrupted", file=sys.stderr)
        return 130
    return run()


if __name__ == "__main__":
    sys.exit(main())
