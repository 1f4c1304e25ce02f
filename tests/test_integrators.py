"""One integrator protocol: the registry keyed by integration method, declared scan needs that the Mapper
checks the same way for every method, and production code that never imports a numpy twin."""

import ast
from pathlib import Path

import numpy as np
import pytest

from evsemmap_warp.config import Compat, Kernel, PayloadType, load_config
from evsemmap_warp.core import integrators as ig
from evsemmap_warp.core.mapper import Mapper

REPO = Path(__file__).resolve().parents[1]
PRESET = REPO / "configs/presets/rellis3d.yaml"
TOY = REPO / "configs/datasets/sbki_toy.yaml"


@pytest.mark.parametrize("files, method, cls", [
    ([PRESET], "ebs", ig.PointKernelIntegrator), ([PRESET], "s-csm", ig.PointKernelIntegrator), ([PRESET], "dempster", ig.PointKernelIntegrator),
    ([PRESET], "convbki", ig.ConvBkiIntegrator), ([PRESET], "see-csom", ig.SeeCsomIntegrator),
    ([TOY], "s-bki", ig.SbkiCompatIntegrator), ([TOY], "s-csm", ig.SbkiCompatIntegrator),
    ([REPO / "configs/presets/release.yaml"], "ebs", ig.ReleaseCompatIntegrator),
])
def test_the_registry_picks_each_methods_integrator(files, method, cls):
    config = load_config(files, method=method).mapping
    integrator = ig.make_integrator(config, 4)
    assert type(integrator) is cls and ig.INTEGRATORS[config.compat, config.kernel] is cls
    assert isinstance(integrator.needs, ig.ScanNeeds)
    # S-CSM's compat cells are centered on multiples of r, half a cell off every other lattice
    assert integrator.grid_offset_m == (-0.5 * config.resolution_m if (config.compat, config.kernel) == (Compat.SBKI, Kernel.COUNT) else 0.0)


def test_every_integration_method_is_registered_once():
    assert set(ig.INTEGRATORS) == {(Compat.CLEAN, k) for k in Kernel} | {(Compat.SBKI, Kernel.SPARSE), (Compat.SBKI, Kernel.COUNT),
                                                                         (Compat.RELEASE, Kernel.SPARSE)}
    with pytest.raises(ValueError, match="two integrators"):
        ig.register_integrator(Compat.CLEAN, Kernel.SPARSE)(type("Another", (), {}))


class _Recorder:
    """A registered integrator that records what the Mapper hands its prepare."""

    grid_offset_m = 0.0
    seen = []

    def __init__(self, config, num_classes):
        self.needs = ig.ScanNeeds(ig.SensorOrigin.REQUIRED, "the recorder measures from it", frozenset({PayloadType.LABEL}), "labels only")

    def prepare(self, scan, device):
        _Recorder.seen.append(scan)
        return ig.launch_step(ig.IntegrationStats(input_points=len(scan.points)))

    def kernel_modules(self, device):
        return []


def test_the_mapper_checks_declared_needs_and_hands_prepare_the_scan_alone(monkeypatch):
    monkeypatch.setitem(ig.INTEGRATORS, (Compat.CLEAN, Kernel.SPARSE), _Recorder)
    mapper = Mapper(load_config([PRESET], method="s-bki").mapping, 3, workers=1, origin=[0.0, 0.0, 0.0])
    points = np.array([[1.0, 2.0, 3.0], [1.5, 2.0, 3.0]])
    with pytest.raises(ValueError, match="payload_type alpha: labels only"):
        mapper.integrate(points, np.full((2, 3), 2.0), payload_type="alpha", sensor_origin=[0, 0, 0])
    with pytest.raises(ValueError, match="sensor_origin: the recorder measures from it; pass it"):
        mapper.integrate(points, np.array([0, 1]), payload_type="label")
    with pytest.raises(ValueError, match="sensor_origin"):
        mapper.integrate(points, np.array([0, 1]), payload_type="label", sensor_origin=[0, np.nan, 0])
    _Recorder.seen.clear()
    mapper.integrate(points, np.array([0, 1]), payload_type="label", sensor_origin=[1.0, 1.0, 1.0])
    (scan,) = _Recorder.seen
    np.testing.assert_array_equal(scan.sensor_origin, [1.0, 1.0, 1.0])  # map coordinates (origin 0 here)
    np.testing.assert_array_equal(scan.points, points)


def test_an_unused_sensor_origin_is_not_handed_on():
    mapper = Mapper(load_config([PRESET], method="ebs").mapping, 3, workers=1)
    seen = []
    mapper.integrator.prepare = lambda scan, device: seen.append(scan) or ig.launch_step(ig.IntegrationStats())
    mapper.integrate(np.zeros((1, 3)), np.full((1, 3), 2.0), payload_type="alpha", sensor_origin=[5.0, 5.0, 5.0])
    assert seen[0].sensor_origin is None


def test_the_release_reads_the_sensor_origin_only_for_its_range_filter():
    config = load_config([REPO / "configs/presets/release.yaml"], method="ebs").mapping
    assert ig.ReleaseCompatIntegrator(config).needs.sensor_origin is ig.SensorOrigin.OPTIONAL  # the preset sets no range
    ranged = config.replace(sbki={"max_range_m": 30.0})
    assert ig.ReleaseCompatIntegrator(ranged).needs.sensor_origin is ig.SensorOrigin.REQUIRED


def _imports(path: Path) -> list[str]:
    tree = ast.parse(path.read_text())
    names = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            names += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            names.append("." * node.level + (node.module or ""))
            names += ["." * node.level + (node.module + "." if node.module else "") + a.name for a in node.names]
    return names


def test_production_code_never_imports_a_numpy_twin():
    # The twins stay independent of what they check: only tests and tools may use them.
    files = [p for p in (REPO / "evsemmap_warp").rglob("*.py") if "reference" not in p.relative_to(REPO / "evsemmap_warp").parts]
    files += list((REPO / "kernels").glob("*.py"))
    assert len(files) > 30
    offenders = {str(p.relative_to(REPO)): n for p in files for n in _imports(p) if "reference" in n.split(".")}
    assert not offenders, f"production modules import numpy twins: {offenders}"


def test_the_map_is_storage_and_knows_no_method():
    # The map holds the table, the rows and the grow-and-relaunch protocol; which kernels a method launches is
    # its integrator's, so a new method never edits the map.
    from evsemmap_warp.core import voxel_map
    from evsemmap_warp.core.voxel_map import VoxelMap

    public = {name for name in vars(VoxelMap) if not name.startswith("_")}
    assert {"launch_until_done", "launch_reserved", "target", "stored_rows"} <= public
    methodish = sorted(n for n in public if any(word in n for word in ("scatter", "gather", "block_cells", "insert_blocks", "kernel")))
    assert not methodish, f"VoxelMap has method-specific entry points: {methodish}"
    kernel_modules = {n.split(".")[-1] for n in _imports(Path(voxel_map.__file__)) if n.startswith("..kernels")}
    assert kernel_modules <= {"kernels", "hash_table", "scatter", "load_once"}, kernel_modules


def test_each_method_is_one_module_of_the_integrators_package():
    classes = set(ig.INTEGRATORS.values())
    modules = {cls.__module__ for cls in classes}
    assert len(modules) == len(classes) == 5
    assert all(m.startswith("evsemmap_warp.core.integrators.") for m in modules), modules


def test_a_launch_refuses_a_scan_status_longer_than_its_counters_read_back():
    import warp as wp

    from evsemmap_warp.core.voxel_map import MAX_SCAN_STATUS, VoxelMap

    vm = VoxelMap(3, 0.5)
    too_long = wp.zeros(MAX_SCAN_STATUS + 1, dtype=int, device=vm.device)
    with pytest.raises(ValueError, match="at most 8 are read back"):
        vm.launch_until_done(1, lambda ids, failed: None, may_insert=False, kind="none", most_new=0, scan_status=too_long)
    status = wp.array(np.arange(3, dtype=np.int32) + 7, dtype=int, device=vm.device)
    assert vm.launch_until_done(1, lambda ids, failed: None, may_insert=False, kind="none", most_new=0, scan_status=status) == 0
    assert vm.counted_status.tolist() == [7, 8, 9]
