"""``evsemmap`` and ``python -m evsemmap_warp``: the command line, answering Ctrl-C in one line from its first
moment. The command line's own imports (Warp, torch, numpy) take a second or more; an interrupt while they
load would otherwise end in an ImportError's traceback."""

import sys


def main() -> int:
    # the command line answers an interrupt while it works itself; this one, one while it loads or reads its flags
    try:
        from .apps.cli import main as run

        return run()
    except KeyboardInterrupt:
        print("evsemmap: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
