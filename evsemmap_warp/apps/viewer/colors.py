"""The viewer's colors: the class palette, the color ramps (viridis for values, blue-white-red for
signed differences), fading, and the legend images (color bars, class swatches)."""

from __future__ import annotations

import numpy as np

from ...classes import named_colors

# Class colors come from configs/classes (docs/algorithm.md §5.1 for the mapping classes); other names get tab10.
CLASS_COLORS = named_colors()
_FALLBACK = np.array([(31, 119, 180), (255, 127, 14), (44, 160, 44), (214, 39, 40), (148, 103, 189),
                      (140, 86, 75), (227, 119, 194), (127, 127, 127), (188, 189, 34), (23, 190, 207)], np.uint8)
# viridis at 9 stops; np.interp between them is indistinguishable at voxel-color precision.
VIRIDIS = np.array([(68, 1, 84), (71, 44, 122), (59, 81, 139), (44, 113, 142), (33, 144, 141),
                    (39, 173, 129), (92, 200, 99), (170, 220, 50), (253, 231, 37)], np.float64)
# blue (the first map surer) - white - red (the second surer), ColorBrewer RdBu
DIVERGING = np.array([(33, 102, 172), (103, 169, 207), (209, 229, 240), (247, 247, 247), (253, 219, 199),
                      (239, 138, 98), (178, 24, 43)], np.float64)
NO_DATA = np.array([128, 128, 128], np.uint8)
TRAJECTORY_COLOR = (255, 140, 0)  # orange (README: "the drive in orange")
SELECTION_COLOR = (255, 0, 0)  # the clicked voxel's wireframe box: a color no class and no other marker has


def class_palette(classes: list[str]) -> np.ndarray:
    """[K, 3] uint8: the class set's color for known class names, a tab10 color otherwise."""
    return np.array([CLASS_COLORS.get(name.lower(), tuple(_FALLBACK[i % len(_FALLBACK)])) for i, name in enumerate(classes)], np.uint8)


def colormap(values: np.ndarray, lo: float, hi: float, stops: np.ndarray = VIRIDIS) -> np.ndarray:
    """[N, 3] uint8 colors of ``values`` on a color ramp (``stops``, viridis by default) over [lo, hi]; NaN grey."""
    finite = np.isfinite(values)
    t = np.clip((np.where(finite, values, lo) - lo) / (hi - lo if hi > lo else 1.0), 0, 1)
    at = np.linspace(0, 1, len(stops))
    out = np.stack([np.interp(t, at, stops[:, c]) for c in range(3)], axis=-1).astype(np.uint8)
    out[~finite] = NO_DATA
    return out


def value_range(values: np.ndarray, percentiles: tuple[float, float] = (0.0, 100.0)) -> tuple[float, float]:
    """(lo, hi): the ``percentiles`` of the finite ``values`` (by default their minimum and maximum); (0, 1) when none is."""
    finite = values[np.isfinite(values)]
    if not len(finite):
        return 0.0, 1.0
    lo, hi = np.percentile(finite, percentiles)
    return float(lo), float(hi)


def diverging(values: np.ndarray, limit: float) -> np.ndarray:
    """Colors of signed ``values`` on a blue-white-red ramp over [-limit, limit]."""
    return colormap(np.asarray(values, np.float64), -limit, limit, DIVERGING)


def faded(colors: np.ndarray, share: float) -> np.ndarray:
    """sRGB colors ``share`` (0..1) of the way to white."""
    colors = np.asarray(colors, np.float64)
    return np.round(colors + share * (255.0 - colors)).astype(np.uint8)


def color_bar_image(lo: float, hi: float, label: str, stops: np.ndarray = VIRIDIS, width: int = 220) -> np.ndarray:
    """A 46-pixel-high color bar with its ends' values and a label (a legend image)."""
    from PIL import Image, ImageDraw

    bar = colormap(np.linspace(lo, hi, 200), lo, hi, stops)
    img = Image.new("RGB", (width, 46), (255, 255, 255))
    img.paste(Image.fromarray(np.repeat(bar[None], 16, axis=0)), (10, 4))
    draw = ImageDraw.Draw(img)
    draw.text((10, 24), f"{lo:.3g}", fill=(0, 0, 0))
    text = f"{hi:.3g}"
    draw.text((210 - 6 * len(text), 24), text, fill=(0, 0, 0))
    draw.text((10, 34), label, fill=(0, 0, 0))
    return np.asarray(img)


def swatch_image(entries: list[tuple[str, tuple]], width: int = 220) -> np.ndarray:
    """A legend of colored squares and names."""
    from PIL import Image, ImageDraw

    img = Image.new("RGB", (width, 18 * len(entries) + 4), (255, 255, 255))
    draw = ImageDraw.Draw(img)
    for k, (name, color) in enumerate(entries):
        draw.rectangle([4, 4 + 18 * k, 18, 18 + 18 * k], fill=tuple(int(c) for c in color), outline=(90, 90, 90))
        draw.text((26, 5 + 18 * k), name, fill=(0, 0, 0))
    return np.asarray(img)
