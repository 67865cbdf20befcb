"""Stress-scenario generator and its CLI."""

import numpy as np
import pytest
import shapely

from roco_env.cli import main
from roco_env.geometry import box_corners_bev
from roco_env.scenario import load_scenario, scenario_from_dict
from roco_env.traffic import make_traffic_source
from roco_env.traffic.generate import generate, nearest_gaps
from roco_env.traffic.opv2v_export import scenario_folder


def test_nearest_gaps_match_shapely_oracle():
    rng = np.random.default_rng(0)
    # a grid of rotated boxes far enough apart not to overlap
    xy = np.stack(np.meshgrid(np.arange(6) * 9.0, np.arange(5) * 7.0), -1).reshape(-1, 2)
    xy += rng.uniform(-0.8, 0.8, xy.shape)
    boxes = np.column_stack([xy, np.ones(len(xy)), rng.uniform(3.5, 5.0, len(xy)),
                             rng.uniform(1.6, 2.0, len(xy)), np.ones(len(xy)),
                             rng.uniform(-0.3, 0.3, len(xy))])
    polys = [shapely.Polygon(c) for c in box_corners_bev(boxes)]
    expected = np.array([min(p.distance(q) for j, q in enumerate(polys) if j != i)
                         for i, p in enumerate(polys)])
    gaps, centre = nearest_gaps(boxes)
    np.testing.assert_allclose(gaps, expected, atol=1e-9)
    assert np.all(centre >= gaps)


def test_generate_writes_a_valid_scenario_and_summary(tmp_path):
    out = tmp_path / "stress.yaml"
    config, summary = generate("parking_lot", 0.9, 4, 1, seed=3, output=out)
    loaded = load_scenario(out)
    assert loaded == config
    assert loaded.traffic.layout == "parking_lot" and loaded.agents.cavs == 4
    assert summary.vehicles > 100
    assert 0.0 < summary.mean_gap < 1.0  # cars side by side in 2.5 m stalls
    sparse = generate("parking_lot", 0.3, 4, 1, seed=3)[1]
    assert sparse.vehicles < summary.vehicles
    with pytest.raises(ValueError, match="layout='merge' is not allowed"):
        generate("merge", 1.0, 1, 0, seed=0)


def test_cli_generate_and_export(tmp_path, capsys):
    out, export = tmp_path / "my.yaml", tmp_path / "opv2v"
    code = main(["scenario", "generate", "--layout", "traffic_jam", "--density", "12",
                 "--cavs", "2", "--rsus", "1", "--seed", "3", "-o", str(out),
                 "--export-opv2v", str(export), "--frames", "3"])
    assert code == 0
    printed = capsys.readouterr().out
    assert "vehicles:" in printed and "nearest-neighbour gap" in printed
    assert "-1" in {p.name for p in scenario_folder(export).iterdir()}  # RSU folder (V2XSet)
    assert f"exported 3 frames to {scenario_folder(export)}" in printed
    replay = make_traffic_source(scenario_from_dict(
        {"traffic": {"source": "opv2v", "path": str(scenario_folder(export))},
         "agents": {"cavs": 2, "rsus": 1}}))
    assert replay.num_frames == 3
    assert main(["scenario", "generate", "--layout", "spaghetti", "--density", "1",
                 "-o", str(out)]) == 2
    assert "spaghetti" in capsys.readouterr().err


def test_export_into_a_non_empty_folder_needs_overwrite(tmp_path, capsys):
    out, export = tmp_path / "my.yaml", tmp_path / "opv2v"

    def export_seed(seed, *extra):
        return main(["scenario", "generate", "--layout", "traffic_jam", "--density", "12",
                     "--cavs", "2", "--rsus", "0", "--seed", str(seed), "-o", str(out),
                     "--export-opv2v", str(export), "--frames", "2", *extra])

    def agent_folders():
        return sorted(p.name for p in scenario_folder(export).iterdir())

    assert export_seed(3) == 0
    first = agent_folders()
    yaml_before = out.read_text()
    assert export_seed(4) == 2  # a second scene would mix with the first
    assert "not empty" in capsys.readouterr().err and agent_folders() == first
    assert out.read_text() == yaml_before  # refused before anything was written
    assert export_seed(4, "--overwrite") == 0
    second = agent_folders()
    replay = make_traffic_source(scenario_from_dict(
        {"traffic": {"source": "opv2v", "path": str(scenario_folder(export))},
         "agents": {"cavs": 2, "rsus": 0}}))
    assert replay.num_frames == 2 and len(second) == 2  # only the new scene's agents
    (export / "notes.txt").write_text("mine")
    assert export_seed(5, "--overwrite") == 2  # never deletes what it did not write
    assert "not OPV2V agent folders" in capsys.readouterr().err
    assert (export / "notes.txt").exists()


@pytest.mark.parametrize("extra, option", [(["--frames", "3"], "--frames"),
                                           (["--overwrite"], "--overwrite")])
def test_export_options_without_an_export_are_refused(tmp_path, capsys, extra, option):
    out = tmp_path / "my.yaml"
    assert main(["scenario", "generate", "--layout", "traffic_jam", "--density", "12",
                 "-o", str(out), *extra]) == 2
    assert f"{option} only applies with --export-opv2v DIR" in capsys.readouterr().err
    assert not out.exists()


def test_the_scenario_output_must_be_a_yaml_file(tmp_path, capsys):
    """list_scenarios and ROCO_ENV_SCENARIOS only see .yaml files; refused before any output."""
    out, export = tmp_path / "my.txt", tmp_path / "opv2v"
    assert main(["scenario", "generate", "--layout", "traffic_jam", "--density", "12",
                 "-o", str(out), "--export-opv2v", str(export)]) == 2
    assert "scenario output: " in capsys.readouterr().err
    assert not out.exists() and not export.exists()


def test_overwrite_replaces_an_export_of_the_older_flat_layout(tmp_path):
    """Exports written before the OpenCOOD layout put the agent folders straight into the
    folder (``<folder>/<agent id>/*.yaml``): --overwrite replaces them too."""
    from roco_env.traffic.opv2v_export import prepare_export_folder

    export = tmp_path / "opv2v"
    for agent in ("641", "650", "-1"):
        (export / agent).mkdir(parents=True)
        (export / agent / "000000.yaml").write_text("lidar_pose: [0, 0, 1.9, 0, 0, 0]\n")
    prepare_export_folder(export, overwrite=True)
    assert list(export.iterdir()) == []
    (export / "641").mkdir()
    (export / "641" / "cloud.pcd").write_bytes(b"points")  # not written by an export
    with pytest.raises(ValueError, match=r"holds \['641'\], which are not OPV2V agent folders"):
        prepare_export_folder(export, overwrite=True)
    assert (export / "641" / "cloud.pcd").exists()
