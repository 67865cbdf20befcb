"""The roco-env subcommands list/run/compare/render: help, outputs, and exit 2 on bad options."""

from __future__ import annotations

import os
import signal
import sys

import pytest
from PIL import Image

from roco_env.cli import main
from roco_env.policies import available_policies

TINY = ["--set", "cavs=2", "--set", "rsus=1"]


@pytest.mark.parametrize("command", ["list", "run", "compare", "render"])
def test_help_everywhere(command, capsys):
    with pytest.raises(SystemExit) as exit_info:
        main([command, "--help"])
    assert exit_info.value.code == 0
    assert f"usage: roco-env {command}" in capsys.readouterr().out


def test_list_shows_scenarios_and_policies(capsys):
    assert main(["list"]) == 0
    out = capsys.readouterr().out
    assert "crowded_intersection" in out and "urban_intersection" in out
    for policy in ("identity", "oracle", "coalign", "roco"):
        assert f"  {policy}\n" in out


@pytest.mark.parametrize("argv, fragments", [
    (["compare", "--policies", "identity", "magic"],
     ["unknown policy 'magic'", ", ".join(available_policies())]),
    (["compare", "--scenario", "atlantis"], ["unknown scenario 'atlantis'", "crowded_intersection"]),
    (["compare", "--backend", "dask"], ["invalid choice: 'dask'", "'local', 'ray'"]),
    (["compare", "--set", "bogus=1"], ["unknown key 'bogus'", "sigma_t"]),
    (["compare", "--noise", "50"], ["sigma_t=50.0 is out of range"]),
    (["compare", "--seeds", "0"], ["--seeds must be >= 1"]),
    (["compare", "--workers", "0"], ["workers must be >= 1"]),
    (["compare", "--address", "auto"], ["only used by the ray backend"]),
    (["compare", "--policies", "oracle:gain=2"], ["policy spec 'oracle:gain=2'"]),
    (["run", "--policy", "magic"], ["unknown policy 'magic'"]),
    (["run", "--scenario", "atlantis"], ["unknown scenario 'atlantis'"]),
    (["run", "--set", "sigma_t=2"], ["'sigma_t' is set by the grid", "--noise / --density"]),
    (["run", "--scenario", "opv2v_replay"], ["needs a dataset folder", "traffic.path"]),
    (["run", "--seed", "-1"], ["seed must be None or an integer >= 0; got -1"]),
    (["render", "--gif", "x.png"], ["--gif must name a .gif file"]),
    (["render"], ["give --out DIR"]),
])
def test_bad_options_exit_2_naming_the_problem(argv, fragments, capsys, tmp_path):
    with pytest.raises(SystemExit) as exit_info:
        raise SystemExit(main([*argv, *(["--out", str(tmp_path)] if argv[0] == "compare" else [])]))
    assert exit_info.value.code == 2
    captured = capsys.readouterr()
    for fragment in fragments:
        assert fragment in captured.err
    assert captured.out == ""  # refused before any episode output
    assert not (tmp_path / "results.jsonl").exists()


def test_run_prints_a_row_per_step_and_the_totals(capsys):
    assert main(["run", "--policy", "oracle", "--steps", "3", "--noise", "0.8", *TINY]) == 0
    out = capsys.readouterr().out.splitlines()
    header = next(i for i, line in enumerate(out) if line.split()[:2] == ["step", "AP@0.5"])
    rows = [line.split() for line in out[header + 1:header + 4]]
    assert [r[0] for r in rows] == ["1", "2", "3"]
    assert all(float(r[4]) < 1e-3 for r in rows)  # oracle: RPE after correction ~ 0
    assert all(r[-1] == "3/3" for r in rows)  # every agent corrected
    assert any(line.startswith("dataset AP@0.3") for line in out)


def test_compare_writes_report_and_resumes(capsys, tmp_path):
    argv = ["compare", "--policies", "identity", "oracle", "--noise", "0", "0.8", "--seeds", "1",
            "--steps", "2", "--workers", "1", "--quiet", "--out", str(tmp_path), *TINY]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "### AP@0.7 (%)" in out and "| oracle |" in out
    assert "(4 run, 0 resumed, 0 recomputed as stale, 0 failed)" in out
    for name in ("results.jsonl", "report.md", "summary.csv", "ap70_vs_noise.png",
                 "rpe_distribution.png"):
        assert (tmp_path / name).stat().st_size > 0
    assert main(argv) == 0
    assert "(0 run, 4 resumed, 0 recomputed as stale, 0 failed)" in capsys.readouterr().out


def test_compare_report_covers_every_result_in_the_folder(capsys, tmp_path):
    base = ["compare", "--noise", "0.4", "--seeds", "1", "--steps", "2", "--workers", "1",
            "--quiet", "--no-plots", "--out", str(tmp_path), *TINY]
    assert main([*base, "--policies", "identity"]) == 0
    assert main([*base, "--policies", "oracle"]) == 0
    out = capsys.readouterr().out
    assert "including 1 from earlier runs" in out
    summary = (tmp_path / "summary.csv").read_text()
    report = (tmp_path / "report.md").read_text()
    for policy in ("identity", "oracle"):
        assert f"| {policy} |" in report and f",{policy}," in summary


def test_render_writes_png_frames_and_a_gif(tmp_path, capsys):
    gif = tmp_path / "episode.gif"
    assert main(["render", "--policy", "identity", "--steps", "2", "--out", str(tmp_path / "png"),
                 "--gif", str(gif), *TINY]) == 0
    frames = sorted((tmp_path / "png").glob("frame_*.png"))
    assert [f.name for f in frames] == ["frame_0001.png", "frame_0002.png"]
    with Image.open(frames[0]) as image:
        assert image.mode == "RGB" and min(image.size) > 100
    with Image.open(gif) as image:
        assert image.n_frames == 2


def test_demo_preset_and_explicit_options_win():
    from roco_env.cli import build_parser
    from roco_env.cli.compare import grid_from_args

    demo = grid_from_args(build_parser().parse_args(["compare", "--demo"]))
    assert {c.scenario for c in demo} == {"crowded_intersection"}
    policies = ["identity", "coalign", "roco", "roco_antialias", "oracle"]
    assert [c.policy for c in demo[::3]][:5] == policies
    assert {c.noise for c in demo} == {0.0, 0.4, 0.8}
    assert len(demo) == 5 * 3 * 3 and {c.steps for c in demo} == {40}
    short = grid_from_args(build_parser().parse_args(["compare", "--demo", "--steps", "2"]))
    assert {c.steps for c in short} == {2} and len(short) == len(demo)


def test_ray_address_without_a_cluster_is_a_clear_error(monkeypatch, capsys, tmp_path):
    ray = pytest.importorskip("ray")

    def no_cluster(*args, **kwargs):
        raise ConnectionError("Could not find any running Ray instance.")

    monkeypatch.setattr(ray, "init", no_cluster)
    argv = ["compare", "--backend", "ray", "--address", "auto", "--policies", "identity",
            "--noise", "0", "--seeds", "1", "--steps", "1", "--quiet", "--out", str(tmp_path)]
    assert main(argv) == 2
    assert "no Ray cluster reachable at address 'auto'" in capsys.readouterr().err


def test_compare_recomputes_after_the_scenario_file_is_edited(capsys, tmp_path):
    scenario = tmp_path / "my.yaml"
    scenario.write_text("agents:\n  cavs: 2\n  rsus: 0\n")
    argv = ["compare", "--scenario", str(scenario), "--policies", "identity", "--noise", "0.4",
            "--seeds", "1", "--steps", "2", "--workers", "1", "--quiet", "--no-plots",
            "--out", str(tmp_path / "out")]
    assert main(argv) == 0
    scenario.write_text("agents:\n  cavs: 3\n  rsus: 0\n")
    capsys.readouterr()
    assert main(argv) == 0
    captured = capsys.readouterr()
    assert "(1 run, 0 resumed, 1 recomputed as stale, 0 failed)" in captured.out
    assert "1 cell(s) recomputed" in captured.err


def test_output_into_a_closed_pipe_ends_quietly(monkeypatch, capsys):
    """`roco-env list | head -1`: the reader left; no 'error: Broken pipe' line, exit 128 + SIGPIPE."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    monkeypatch.setattr(sys, "stdout", os.fdopen(write_end, "w"))
    assert main(["list"]) == 128 + signal.SIGPIPE
    assert capsys.readouterr().err == ""


def test_train_detector_on_cuda_without_a_cuda_device_exits_2_before_any_work(
        monkeypatch, capsys, tmp_path):
    torch = pytest.importorskip("torch")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert main(["train-detector", "--out", str(tmp_path / "det"), "--device", "cuda",
                 "--steps", "1", "--train-scenes", "1", "--val-scenes", "0", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "device='cuda' (--device cuda) but torch" in err and "sees no CUDA device" in err
    assert "generating" not in err  # refused before the scenes were made


def test_run_and_compare_say_when_a_replay_ends_before_the_steps_asked_for(tmp_path, capsys):
    from roco_env.traffic.generate import generate
    from roco_env.traffic.opv2v_export import scenario_folder

    generate("traffic_jam", 12.0, 2, 0, seed=0, export_dir=tmp_path / "scene", frames=2)
    scene = scenario_folder(tmp_path / "scene")
    assert main(["run", "--scenario", "opv2v_replay", "--set", f"traffic.path={scene}",
                 "--policy", "identity", "--steps", "5"]) == 0
    out = capsys.readouterr().out
    assert "the episode ended after 2 of 5 steps: the scenario's frames ran out" in out
    assert main(["run", "--policy", "identity", "--steps", "2", *TINY]) == 0
    assert "the episode ended" not in capsys.readouterr().out
    for name, steps in (("replay", "5"), ("synthetic", "2")):
        scenario = ["--scenario", "opv2v_replay", "--set", f"traffic.path={scene}"] \
            if name == "replay" else TINY
        assert main(["compare", *scenario, "--policies", "identity", "--noise", "0",
                     "--seeds", "1", "--steps", steps, "--no-plots", "--quiet",
                     "--out", str(tmp_path / name)]) == 0
    report = (tmp_path / "replay" / "report.md").read_text()
    assert "Episodes of 5 steps;" in report
    assert "Episodes that ran out of frames ended sooner: opv2v_replay after 2 of 5 steps." in report
    assert "ran out of frames" not in (tmp_path / "synthetic" / "report.md").read_text()


def test_compare_sweeps_any_scenario_field_with_grid_and_resumes(capsys, tmp_path):
    argv = ["compare", "--policies", "identity", "--noise", "0", "--seeds", "1", "--steps", "2",
            "--workers", "1", "--quiet", "--no-plots", "--out", str(tmp_path), *TINY,
            "--set", "delay=fixed", "--grid", "delay_ms=0,100,200"]
    assert main(argv) == 0
    out = capsys.readouterr().out
    assert "### AP@0.7 (%) vs delay_ms (noise 0.0/0.0)" in out
    assert "| Policy \\ delay_ms | 0 | 100 | 200 |" in out
    assert "### Bytes received per agent-step vs delay_ms (noise 0.0/0.0)" in out
    assert "(3 run, 0 resumed" in out
    assert main(argv) == 0
    assert "(0 run, 3 resumed" in capsys.readouterr().out
    assert main([*argv[:-1], "delay_ms=100,-5"]) == 2
    assert "comm.delay_params.delay_ms=-5" in capsys.readouterr().err
