"""The experiment runner end to end on the tiny synthetic world, its caching, and its config errors."""

import json

import pytest

from evsemmap_warp.apps.cli import main
from evsemmap_warp.config import ConfigError
from evsemmap_warp.apps.experiment import Experiment, load_experiment

CONFIG = """
name: tiny-study
sequences:
  train: {world: tiny, seed: 3, frames: 4}
  test: {world: tiny}
networks:
  net: {train_on: [train], epochs: 1, batch_size: 2, input_size: [64, 128]}
conditions:
  in-domain: {network: net, sequence: test}
mapping_preset: offroad
methods: [s-csm, ebs]
ablation: {condition: in-domain, methods: [s-bki, prob, convbki]}
convbki: {window_scans: 2, windows: 2, queries_per_window: 300, epochs: 1}
"""


def test_study_runs_writes_everything_and_reruns_from_cache(tmp_path):
    path = tmp_path / "study.yaml"
    path.write_text(CONFIG)
    config, _ = load_experiment(path)
    out = tmp_path / "out"
    first = Experiment(config, out, progress=False, log=lambda m: None)
    results = first.run()
    assert set(results["in-domain"]) == {"s-csm", "ebs", "s-bki", "prob", "convbki"}
    lengths = list((out / "cache" / "convbki").glob("net-*.json"))
    assert len(lengths) == 1 and "ell_h" in json.loads(lengths[0].read_text())
    assert any(k.startswith("train") for k in first.timings) and any(k.startswith("render") for k in first.timings)
    for name in ("results.md", "scores.csv", "scores.json", "record.json", "iou_in-domain.png", "ablation.png",
                 "maps/in-domain/ebs.npz", "maps/in-domain/s-csm.npz", "maps/in-domain/trajectory.txt"):
        assert (out / name).exists(), name
    text = (out / "results.md").read_text()
    assert "## in-domain" in text and "## Ablation (in-domain)" in text and "| ebs |" in text
    scores = json.loads((out / "scores.json").read_text())
    assert scores["in-domain"]["s-csm"]["scored_queries"] > 100
    import numpy as np

    trajectory = np.loadtxt(out / "maps/in-domain/trajectory.txt")
    # the maps' frame is the sequence's own (its poses as given), and the maps say so
    from evsemmap_warp.core.mapper import load_map
    from evsemmap_warp.data.sequences import read_poses

    evaluated = first.sequence_dir(config.conditions["in-domain"].sequence)
    assert trajectory.shape == (6, 3) and np.allclose(trajectory, read_poses(evaluated / "poses.txt")[:, :3, 3], atol=1e-4)
    assert load_map(out / "maps/in-domain/ebs.npz").frame.name == "odom"
    record = json.loads((out / "record.json").read_text())
    assert record["versions"]["warp"] and record["experiment"]["name"] == "tiny-study"

    # One more method: nothing is rendered or trained again, and the finished maps are reused.
    ebs_mtime = (out / "maps/in-domain/ebs.npz").stat().st_mtime_ns
    path.write_text(CONFIG.replace("methods: [s-csm, ebs]", "methods: [s-csm, ebs, prob-thr]"))
    config, _ = load_experiment(path)
    second = Experiment(config, out, progress=False, log=lambda m: None)
    second.run()
    assert not any(k.startswith(("train", "render", "infer", "convbki")) for k in second.timings)
    assert (out / "maps/in-domain/ebs.npz").stat().st_mtime_ns == ebs_mtime
    assert (out / "maps/in-domain/prob-thr.npz").exists()


@pytest.mark.parametrize("change, message", [
    ("methods: [s-csm, ebs]", "unknown method 'nope'"),
    ("in-domain: {network: net, sequence: test}", "conditions.in-domain names network 'other'"),
    ("test: {world: tiny}", "needs exactly one of world"),
])
def test_config_errors_come_before_any_work(tmp_path, change, message):
    replacement = {"methods: [s-csm, ebs]": "methods: [s-csm, nope]",
                   "in-domain: {network: net, sequence: test}": "in-domain: {network: other, sequence: test}",
                   "test: {world: tiny}": "test: {world: tiny, path: /x}"}[change]
    path = tmp_path / "bad.yaml"
    path.write_text(CONFIG.replace(change, replacement))
    with pytest.raises(ConfigError, match=message):
        load_experiment(path)


def test_builtin_experiment_configs_load(capsys):
    for name in ("demo", "paper-main", "paper-robustness", "paper-ablation", "rellis3d-5fold", "paper-unseen"):
        config, _ = load_experiment(name)
        assert config.conditions and config.methods
    assert main(["experiment", "no-such-study"]) == 2
    assert "no such experiment config" in capsys.readouterr().err


def test_interrupted_training_resumes_from_its_last_epoch(tmp_path, monkeypatch):
    import dataclasses

    import evsemmap_warp.segmentation.train as train_module

    path = tmp_path / "study.yaml"
    path.write_text(CONFIG.replace("epochs: 1,", "epochs: 2,"))
    config, _ = load_experiment(path)
    real_train = train_module.train

    def killed_after_first_epoch(source, names, train_config, out_dir, **kw):
        real_train(source, names, dataclasses.replace(train_config, epochs=1), out_dir, **kw)
        (out_dir / "metrics.json").unlink()  # the summary is written last: a kill leaves only checkpoints
        raise KeyboardInterrupt

    monkeypatch.setattr(train_module, "train", killed_after_first_epoch)
    with pytest.raises(KeyboardInterrupt):
        Experiment(config, tmp_path / "out", progress=False, log=lambda m: None).network("net")
    monkeypatch.setattr(train_module, "train", real_train)
    messages = []
    best = Experiment(config, tmp_path / "out", progress=False, log=messages.append).network("net")
    assert any("(resuming)" in m for m in messages)
    history = json.loads((best.parent / "history.json").read_text())
    assert [h["epoch"] for h in history] == [1, 2]
    # killed after the last epoch: only the summary is redone, nothing is trained again
    (best.parent / "metrics.json").unlink()
    again = Experiment(config, tmp_path / "out", progress=False, log=lambda m: None)
    assert again.network("net") == best and (best.parent / "metrics.json").exists()
    assert not any(k.startswith("train") for k in again.timings)


def test_conditions_pool_into_one_table(tmp_path):
    """Two conditions on two worlds, pooled as the RELLIS-3D folds are (docs/algorithm.md §4.5), ablation on the pool."""
    text = CONFIG.replace("  test: {world: tiny}", "  test: {world: tiny}\n  test-b: {world: tiny, seed: 4, frames: 3}")
    text = text.replace("  in-domain: {network: net, sequence: test}", "  in-domain: {network: net, sequence: test}\n  other: {network: net, sequence: test-b}")
    text = text.replace("ablation: {condition: in-domain, methods: [s-bki, prob, convbki]}", "ablation: {condition: both, methods: [s-bki, prob]}")
    path = tmp_path / "pooled.yaml"
    path.write_text(text + "pools:\n  both: [in-domain, other]\n")
    config, _ = load_experiment(path)
    results = Experiment(config, tmp_path / "out", progress=False, log=lambda m: None).run()
    pooled, parts = results["pool:both"]["s-csm"], [results["in-domain"]["s-csm"], results["other"]["s-csm"]]
    assert (pooled.confusion == parts[0].confusion + parts[1].confusion).all()
    assert pooled.scored_queries == sum(p.scored_queries for p in parts)
    assert set(results["pool:both"]) >= {"s-csm", "ebs", "s-bki", "prob"}  # the ablation ran on every member
    text = (tmp_path / "out" / "results.md").read_text()
    assert "## Pooled: both" in text and "## Ablation (both)" in text
    assert "pool:both" in (tmp_path / "out" / "scores.csv").read_text()
    path.write_text(CONFIG + "pools:\n  bad: [nowhere]\n")
    with pytest.raises(ConfigError, match="pools.bad must list conditions defined above"):
        load_experiment(path)


def test_a_study_on_robot_logs_scores_as_on_their_folders(tmp_path):
    """Sequences given as logs (ROS 1 bag, MCAP) train, infer, project and score exactly as the same
    drives given as folders."""
    pytest.importorskip("rosbags")
    from evsemmap_warp.data.log_writer import write_log
    from evsemmap_warp.synthetic.preset import load_preset
    from evsemmap_warp.synthetic.writer import generate_sequence

    folders = {name: tmp_path / name for name in ("train", "test")}
    generate_sequence(load_preset("tiny", seed=3, trajectory__frames=4), folders["train"], progress=False)
    generate_sequence(load_preset("tiny"), folders["test"], progress=False)
    logs = {"train": tmp_path / "train.bag", "test": tmp_path / "test.mcap"}
    write_log(folders["train"], logs["train"], "rosbag1")
    write_log(folders["test"], logs["test"], "mcap")
    study = """
name: paths
sequences:
  train: {{path: {train}}}
  test: {{path: {test}}}
networks:
  net: {{train_on: [train], epochs: 1, batch_size: 2, input_size: [64, 128]}}
conditions:
  in-domain: {{network: net, sequence: test}}
mapping_preset: offroad
methods: [s-csm, ebs]
"""
    scores = {}
    for kind, paths in (("folders", folders), ("logs", logs)):
        path = tmp_path / f"{kind}.yaml"
        path.write_text(study.format(**{k: str(v) for k, v in paths.items()}))
        config, _ = load_experiment(path)
        results = Experiment(config, tmp_path / kind, progress=False, log=lambda m: None).run()
        scores[kind] = {m: (s.miou, s.accuracy, s.extra["voxels"]) for m, s in results["in-domain"].items()}
    assert scores["folders"]["ebs"][2] > 100
    for method, (miou, accuracy, voxels) in scores["folders"].items():
        log_miou, log_accuracy, log_voxels = scores["logs"][method]
        assert voxels == log_voxels and abs(miou - log_miou) < 1e-9 and abs(accuracy - log_accuracy) < 1e-9, method
