"""The config's enumerations: the values a config file may give ``mapping.kernel``, ``mapping.fusion``,
``mapping.media``, ``mapping.threshold_scope``, ``mapping.compat``, ``mapping.clean.scatter_strategy`` and
``dataset.payload``."""

from __future__ import annotations

import enum


class Kernel(str, enum.Enum):
    """How a point spreads its evidence over the voxels around it (``mapping.kernel``). A kernel other
    than sparse and count comes with its method's own integration (``core.integrators``)."""
    SPARSE = "sparse"  # BKI sparse kernel k'(d, l, sigma0)
    COUNT = "count"  # counting sensor model: weight 1 inside the point's own voxel
    COMPOUND = "compound"  # ConvBKI's per-class compound kernel on a voxel-center stencil (docs/compatibility.md §2)
    TRIANGULAR = "triangular"  # SEE-CSOM's triangular kernel on entropy-gated blocks (docs/compatibility.md §3)


class Fusion(str, enum.Enum):
    """How the evidence that reaches a voxel combines (``mapping.fusion``)."""
    BAYES = "bayes"  # Dirichlet concentrations add up (every BKI / CSM method)
    DEMPSTER = "dempster"  # belief masses fused with Dempster's rule (docs/algorithm.md §3.7)


class Media(str, enum.Enum):
    """What a point contributes per class (``mapping.media``), whatever its payload (``PayloadType``)."""
    ONEHOT = "onehot"  # one-hot of the payload's argmax class, lowest index on ties (S-CSM, S-BKI)
    SOFT = "soft"  # the class-probability vector: alpha / S for alpha payloads (EBS, the "Prob." ablations)


class ThresholdScope(str, enum.Enum):
    """Over which points the uncertainty threshold drops its fraction (``mapping.threshold_scope``)."""
    INSERTION = "insertion"  # the most uncertain points of the whole insertion (the paper)
    # the most uncertain points of each class the network predicted, in each insertion: a class the network is
    # unsure of as a whole (small objects, rare ground) keeps its surest points instead of losing most of them
    PREDICTED_CLASS = "predicted-class"


class Compat(str, enum.Enum):
    """Which program's map to compute: the paper's algorithm or one of the original C++ programs
    (``mapping.compat``)."""
    CLEAN = "clean"  # the paper's algorithm with a true radius search (default)
    SBKI = "sbki"  # reproduce the original S-BKI / S-CSM C++ (docs/compatibility.md §1)
    RELEASE = "release"  # reproduce the released EvSemMap C++ for ebs / dempster (docs/compatibility.md §4)


class PayloadType(str, enum.Enum):
    """What a scan's per-point payload holds, and so how ``Mapper.integrate`` reads it (``Media`` says what
    a point then contributes to the map)."""
    ALPHA = "alpha"  # evidential Dirichlet parameters, [N, K], alpha >= 1
    PROB = "prob"  # class probabilities, [N, K], rows sum to 1
    LABEL = "label"  # integer class ids, [N]


class ScatterStrategy(str, enum.Enum):
    """How the radius kernel (clean mode, Bayes fusion) reaches the map (``mapping.clean.scatter_strategy``);
    sorted and gather sum each voxel in a fixed order (docs/kernel_study.md)."""
    ATOMIC = "atomic"  # scatter with atomic adds
    SORTED = "sorted"  # sort-then-reduce
    GATHER = "gather"  # per voxel, through a hash grid of the points
