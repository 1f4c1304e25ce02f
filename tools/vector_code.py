"""What the CPU compiler made of the hot kernels: their vector instructions, counted in the disassembly.

    python tools/vector_code.py [--classes 9]

Builds the compatibility modes' block gathers (S-BKI, release EBS and Dempster) and the clean-mode scatter
for the CPU, as a map with ``--classes`` classes does, and counts in each one's object file (``objdump -d``
of Warp's kernel cache) the instructions on 512- and 256-bit registers, the packed float arithmetic among
them and the fused multiply-adds. A change that makes the compiler give up a kernel's vector code shows as
a drop in its packed arithmetic; the counts depend on the CPU (Warp builds for the host's own,
``-march=native``), so compare them on one machine. Needs ``objdump`` (binutils).
"""

from __future__ import annotations

import argparse
import glob
import os
import re
import shutil
import subprocess
import sys

PACKED_ARITHMETIC = re.compile(r"\bv(?:add|sub|mul|div|fmadd\w*|fmsub\w*|max|min|sqrt)p[sd]\b.*\b[yz]mm")


def kernels(num_classes: int) -> dict:
    """name -> kernel of the hot kernels a map of ``num_classes`` classes launches."""
    from evsemmap_warp.config import load_config
    from evsemmap_warp.core.integrators import make_integrator, scatter_fusion
    from evsemmap_warp.kernels import scatter as sc

    sys.path.insert(0, os.path.dirname(__file__))
    import bench_integrate as bench

    sbki = make_integrator(bench.compat_config(0.5), num_classes)
    out = {"S-BKI gather": sbki.gather_kernel(num_classes, sbki.cells_per_block)}
    for method in ("ebs", "dempster"):
        config = load_config([bench.RELEASE_PRESET], method=method).mapping
        release = make_integrator(config, num_classes)
        out[f"release gather ({method})"] = release.gather_kernel(num_classes, release.cells_per_block, fusion=scatter_fusion(config))
    out["clean scatter (radius, class weights)"] = sc.scatter_kernel(sc.MODE_RADIUS, sc.FUSION_BAYES, False)
    return out


def object_file(kernel) -> str:
    """The CPU object file Warp built for ``kernel``'s module (built now if it was not)."""
    import warp as wp

    from evsemmap_warp.kernels import load_once

    load_once(kernel.module, "cpu")
    identifier = kernel.module.get_module_identifier()  # wp_<name>_<hash>: its cache folder adds a build hash
    folders = sorted(glob.glob(os.path.join(wp.config.kernel_cache_dir, identifier[:-7] + "*")), key=os.path.getmtime)
    return glob.glob(os.path.join(folders[-1], "*.o"))[0]


def counts(path: str) -> dict:
    lines = subprocess.run(["objdump", "-d", "--no-show-raw-insn", path], capture_output=True, text=True, check=True).stdout.splitlines()
    return {"zmm": sum("zmm" in line for line in lines), "ymm": sum("ymm" in line for line in lines),
            "packed arithmetic": sum(bool(PACKED_ARITHMETIC.search(line)) for line in lines), "fma": sum("vfmadd" in line or "vfmsub" in line for line in lines)}


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--classes", type=int, default=9)
    args = parser.parse_args()
    if shutil.which("objdump") is None:
        print("objdump is not installed (binutils): nothing to disassemble", file=sys.stderr)
        return 2
    from evsemmap_warp.core.warp_runtime import init_warp

    init_warp()
    print(f"{'kernel':40s} {'zmm':>5s} {'ymm':>5s} {'packed arith':>12s} {'fma':>5s}")
    for name, kernel in kernels(args.classes).items():
        c = counts(object_file(kernel))
        print(f"{name:40s} {c['zmm']:5d} {c['ymm']:5d} {c['packed arithmetic']:12d} {c['fma']:5d}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
