"""``evsemmap`` and ``python -m evsemmap_warp``: the command line, answering Ctrl-C in one line from its first
moment. The command line's own imports (Warp, torch, numpy) take a second or more; an interrupt while they
load would otherwise end in an ImportError's traceback."""

import os
import sys


def main() -> int:
    # The command line is a program of its own, so it may choose a setting of its whole process, which the
    # library never does: numpy's transparent-huge-page advice off (numpy reads this at import, below) halves a
    # map's read-out on the VMs measured (docs/performance.md, "Measurements behind the code's choices",
    # core/mapper.py). A run's environment that sets the variable keeps its own choice.
    os.environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")
    # the command line answers an interrupt while it works itself; this one, one while it loads or reads its flags
    try:
        from .apps.cli import main as run

        return run()
    except KeyboardInterrupt:
        print("evsemmap: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
