"""The kernel family: kernels specialised when built (no kernel takes a method switch or more than a dozen
arguments), every scatter combination built once, and each method's weight rule against its numpy twin."""

import importlib
import pkgutil

import numpy as np
import pytest
import warp as wp

from evsemmap_warp import kernels as kernel_package
from evsemmap_warp.kernels import MODULE_OPTIONS
from evsemmap_warp.kernels import block_gather, hashgrid_gather, microbench, release, sorted_scatter
from evsemmap_warp.kernels import scatter as sc
from evsemmap_warp.reference import scatter as ref

# A kernel with more arguments than this carries loose state that belongs in a struct.
MAX_KERNEL_ARGUMENTS = 12
# Arguments that would mean a kernel branches on a method at run time.
METHOD_SWITCHES = {"mode", "fusion", "use_labels", "media", "payload_type"}
# Every module of kernels/, so that a kernel anywhere in it is checked (as tests/test_twins.py finds them).
KERNEL_MODULES = tuple(sorted(m.name for m in pkgutil.iter_modules(kernel_package.__path__)))


def _every_kernel():
    """(name, kernel) for every module-level kernel of every module of kernels/ and a made instance of every factory."""
    made = {
        "scatter_points": [sc.scatter_kernel(mode, fusion, labels) for (mode, fusion, labels) in sc._SCATTER_KERNELS],
        "weight_rule_values": [sc.weight_rule_kernel(mode) for mode in sc.SCATTER_MODES],
        "reduce_voxels": [sorted_scatter.reduce_voxels_kernel(labels) for labels in (True, False)],
        "gather_voxels": [hashgrid_gather.gather_voxels_kernel(labels) for labels in (True, False)],
        "gather_sbki_blocks": [block_gather.gather_sbki_kernel(9, 2)],
        "gather_release_blocks": [release.gather_release_kernel(9, 2, fusion=f) for f in (sc.FUSION_BAYES, sc.FUSION_DEMPSTER)],
        "block_models": [release.block_models_kernel(dense) for dense in (True, False)],
        "sorted_rows": [release.sorted_rows_kernel(9, dempster) for dempster in (False, True)],
        "radix_scatter_form": [microbench.radix_scatter_form(w, m) for w in (True, False) for m in (True, False)],
    }
    out = []
    for module_name in KERNEL_MODULES:
        module = importlib.import_module(f"evsemmap_warp.kernels.{module_name}")
        out += [(f"{module_name}.{n}", k) for n, k in vars(module).items() if isinstance(k, wp.Kernel)]
        for name in getattr(module, "KERNEL_FACTORIES", {}):
            assert name in made, f"{module_name}.{name}: a kernel factory this test does not make an instance of"
            out += [(f"{module_name}.{name}", k) for k in made[name]]
    return out


def test_no_kernel_takes_a_method_switch_or_loose_state():
    kernels = _every_kernel()
    assert len(kernels) > 20
    for name, kernel in kernels:
        args = list(kernel.adj.args)
        assert len(args) <= MAX_KERNEL_ARGUMENTS, f"{name} takes {len(args)} arguments: {[a.label for a in args]}"
        switches = METHOD_SWITCHES & {a.label for a in args}
        assert not switches, f"{name} branches at run time on {switches}: specialise it when it is built"


def test_every_kernel_is_built_with_the_package_options():
    # A kernel in a module of its own (module="unique") does not take its file's wp.set_module_options.
    # Without them the block gathers and the rows kernels compiled their adjoints, more than half of the
    # gathers' first-use compile (docs/performance.md), and a CUDA build fuses multiply-adds that the CPU
    # build does not (fuse_fp), so that its results would not be the CPU's bit for bit.
    assert MODULE_OPTIONS == {"enable_backward": False, "fuse_fp": False}
    for name, kernel in _every_kernel():
        options = kernel.module.options | kernel.options
        assert not options["enable_backward"], f"{name} compiles a backward pass"
        assert not options["fuse_fp"], f"{name} lets a CUDA build fuse multiply-adds"


def test_every_valid_scatter_combination_is_built_once_and_the_others_are_refused():
    assert len(sc._SCATTER_KERNELS) == 10
    assert len({id(k) for k in sc._SCATTER_KERNELS.values()}) == 10
    assert sc.scatter_kernel(sc.MODE_RADIUS, sc.FUSION_DEMPSTER, False) is sc._SCATTER_KERNELS[sc.MODE_RADIUS, sc.FUSION_DEMPSTER, False]
    for combination in [(sc.MODE_STENCIL, sc.FUSION_BAYES, True), (sc.MODE_RADIUS, sc.FUSION_DEMPSTER, True),
                        (sc.MODE_OWN_VOXEL, sc.FUSION_DEMPSTER, False)]:
        with pytest.raises(ValueError, match="no scatter for mode"):
            sc.scatter_kernel(*combination)
    # only the clean modes insert; the compat modes' cells are inserted beforehand
    assert [m for m in sc.SCATTER_MODES if sc.scatter_inserts(m)] == [sc.MODE_RADIUS, sc.MODE_OWN_VOXEL, sc.MODE_STENCIL]


@pytest.mark.parametrize("mode", sorted(sc.SCATTER_MODES))
def test_each_weight_rule_matches_its_twin(mode):
    rng = np.random.default_rng(30 + mode)
    n, k, res, half = 300, 5, 0.2, 2
    points = rng.uniform(-2.0, 2.0, (n, 3))
    lengths = rng.uniform(0.1, 0.5, n)
    class_weights = rng.dirichlet(np.ones(k), n)
    stencil = rng.uniform(0.0, 1.0, ((2 * half + 1) ** 3, k)) * (rng.random(((2 * half + 1) ** 3, 1)) < 0.8)  # some offsets of no mass
    own = np.floor(points / res).astype(np.int64)
    pair_point = np.repeat(np.arange(n), 20)
    pair_cell = own[pair_point] + rng.integers(-half, half + 1, (len(pair_point), 3))
    d = wp.get_device("cpu")
    scan = sc.scan_points(points=wp.array(points, dtype=wp.vec3d, device=d), lengths=wp.array(lengths, dtype=wp.float64, device=d),
                          class_weights=wp.array(class_weights, dtype=wp.float64, device=d),
                          owner_blocks=wp.array(np.floor(points / (2 * res) + 0.5).astype(np.int32), dtype=wp.vec3i, device=d))
    params = sc.scatter_params(resolution=res, grid_offset=0.0, sigma0=10.0, cells_per_block=2,
                               stencil_weights=wp.array(stencil, dtype=wp.float64, device=d), stencil_half=half)
    out = wp.empty(len(pair_point), dtype=wp.float64, device=d)
    wp.launch(sc.weight_rule_kernel(mode), dim=len(pair_point), device=d, inputs=[
        scan, params, wp.array(pair_point.astype(np.int32), dtype=int, device=d), wp.array(pair_cell.astype(np.int32), dtype=wp.vec3i, device=d), out])
    want = ref.weight_rule_values(mode, points, lengths, class_weights, pair_point, pair_cell, resolution=res, grid_offset=0.0, sigma0=10.0,
                                  stencil_weights=stencil)
    got = out.numpy()
    assert (want > 0).any() and (want == 0).any() or mode in (sc.MODE_OWN_VOXEL, sc.MODE_SBKI_OWN_BLOCK)
    if mode == sc.MODE_SBKI_BLOCKS:
        # float32 on both sides, from the same float32 operations: at most an ulp of sf2 apart
        np.testing.assert_allclose(got, want, rtol=2e-7, atol=10.0 * 2e-7)
    else:
        # float64: the twin's distance (a norm) and the kernel's (squared offsets summed) differ by an ulp or two
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-14)


def _integrator_config(case: str):
    """The mapping config of an integrator test case: METHOD, METHOD@sbki or METHOD@release (the compat
    modes; +device: their preprocessing on the map's device, as on a GPU), or ebs/STRATEGY (the radius
    kernel's other scatter strategies)."""
    import dataclasses

    from conftest import REPO

    from evsemmap_warp.config import Compat, ScatterStrategy, load_config

    method, _, variant = case.replace("/", "@").removesuffix("+device").partition("@")
    if variant == "release":
        return load_config([REPO / "configs/presets/release.yaml"], method=method).mapping
    config = load_config([REPO / "configs/presets/rellis3d.yaml"], method=method).mapping
    if variant == "sbki":
        return dataclasses.replace(config, compat=Compat.SBKI)
    if variant:
        return dataclasses.replace(config, clean=dataclasses.replace(config.clean, scatter_strategy=ScatterStrategy(variant)))
    return config


@pytest.mark.parametrize("case", ["ebs", "ebs/sorted", "ebs/gather", "s-csm", "dempster", "convbki", "see-csom", "s-bki@sbki", "s-csm@sbki",
                                  "ebs@release", "dempster@release", "s-bki@sbki+device", "ebs@release+device"])
def test_a_mapper_loads_every_kernel_module_it_launches_before_its_first_scan(case, monkeypatch):
    # The Mapper compiles its integrator's modules up front, in the calling thread (Warp's compiler keeps
    # its precompiled headers per thread; a module a prepare or shard thread compiled first built them
    # again), and only those: a clean-mode map needs the hash table and its one scatter.
    from warp._src.context import get_module

    from evsemmap_warp.core.mapper import Mapper
    from evsemmap_warp.kernels import hash_table

    def warp_module(module):
        return module if isinstance(module, wp.Module) else get_module(module.__name__)

    mapper = Mapper(_integrator_config(case), 9, workers=2)
    if case.endswith("+device"):
        mapper.integrator.preprocess_on_device = True
    declared = {warp_module(m) for m in mapper.integrator.kernel_modules(mapper.device)} | {warp_module(hash_table)}
    launched = set()
    original = wp.launch

    def launch(kernel, *args, **kwargs):
        launched.add(kernel.module)
        return original(kernel, *args, **kwargs)

    monkeypatch.setattr(wp, "launch", launch)
    rng = np.random.default_rng(4)
    scans = []
    for i in range(3):
        points = rng.uniform(-6.0, 6.0, (3000, 3)) * [1.0, 1.0, 0.2] + [i * 0.5, 0.0, 0.0]
        alpha = np.ones((3000, 9))
        alpha[np.arange(3000), rng.integers(1, 9, 3000)] += rng.gamma(2.0, 50.0, 3000)
        scans.append(type("Scan", (), {"points": points, "payload": alpha, "payload_type": "alpha", "sensor_origin": np.array([i * 0.5, 0.0, 1.5])}))
    stats = mapper.integrate_many(scans)
    assert sum(s.voxel_updates for s in stats) > 0
    assert launched, "nothing was launched"
    missing = sorted(m.name for m in launched - declared)
    assert not missing, f"{case}: launched kernels of modules its integrator does not declare: {missing}"
    if "@" not in case and "/" not in case and case != "see-csom":
        assert len(declared) == 2  # the hash table and the scatter: nothing else compiles for a clean-mode map
