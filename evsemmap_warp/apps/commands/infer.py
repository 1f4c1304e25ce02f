"""``evsemmap infer``: per-frame Dirichlet alpha (float16 .npy) from a trained checkpoint."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np

from .args import positive


def add_parser(sub) -> None:
    """Add ``infer`` to the ``evsemmap`` subcommands."""
    p = sub.add_parser("infer", help="per-frame Dirichlet alpha (float16 .npy) from a trained checkpoint")
    p.add_argument("checkpoint", type=Path)
    p.add_argument("images", type=Path, help="an image or a folder of .jpg/.png images")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--batch-size", type=positive, default=4)
    p.add_argument("--quiet", action="store_true")
    p.set_defaults(func=run)


def run(args) -> int:
    """Write the per-image Dirichlet alpha of a checkpoint (float16 .npy) for an image or a folder of them."""
    from PIL import Image
    from tqdm import tqdm

    from ...files import save_npy_atomically
    from ...segmentation.train import infer_alpha, load_checkpoint

    model, config, meta, _ = load_checkpoint(args.checkpoint)
    paths = sorted(p for p in args.images.iterdir() if p.suffix.lower() in (".jpg", ".jpeg", ".png")) if args.images.is_dir() else [args.images]
    if not paths:
        raise ValueError(f"{args.images}: no .jpg or .png images")
    args.out.mkdir(parents=True, exist_ok=True)

    def images():
        for path in paths:
            with Image.open(path) as img:
                if img.mode != "RGB":
                    raise ValueError(f"{path}: expected an RGB image, got mode {img.mode}")
                yield np.asarray(img)

    outputs = infer_alpha(model, config, meta, images(), batch_size=args.batch_size)
    for path, (alpha, _) in tqdm(zip(paths, outputs), total=len(paths), unit="img", disable=args.quiet):
        save_npy_atomically(args.out / f"{path.stem}.npy", alpha)
    print(f"wrote {len(paths)} {'alpha' if config.head == 'evidential' else 'probability'} maps "
          f"[{config.model.num_classes}, {config.input_size[0]}, {config.input_size[1]}] float16 to {args.out}", file=sys.stderr)
    return 0
