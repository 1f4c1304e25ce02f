"""Array indices in a form the CPU compiler can use (Warp functions, no kernels).

Warp wraps a negative array index as Python does (``a[-1]``): every access to an index the compiler
cannot prove non-negative carries a compare and an add on the way to its address. It cannot prove it
for an index read from an array (a slot, a cursor, a point id) or for the counter of a
``for i in range(n)`` loop with a bound known only at run time, whose iterator Warp keeps in a struct;
it can for the counter of a ``while`` loop that starts at 0 and counts up. The host preprocessing
kernels walk whole arrays in one thread (launched with dim=1), where these few instructions sit on
every element's path: they loop with ``while`` and pass the indices they read through ``nonnegative``.
On CUDA the same code costs one AND per index.
"""

import warp as wp

from . import MODULE_OPTIONS

wp.set_module_options(MODULE_OPTIONS)

# The one-thread host kernels loop with while and index through ``nonnegative``; the gathers stay range
# loops (docs/performance.md, "Measurements behind the code's choices").
_NON_NEGATIVE_INT = wp.constant(0x7FFFFFFF)


@wp.func
def nonnegative(index: int) -> int:
    """``index`` itself, for 0 <= index, in a form the compiler sees cannot be negative (the sign bit
    masked off), so that the array access it feeds skips Warp's wrap of negative indices."""
    return index & _NON_NEGATIVE_INT
