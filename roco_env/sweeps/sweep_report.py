"""Write a sweep's report: ``report.md`` (tables), ``summary.csv`` and PNG plots.

Layout of ``report.md``: per scenario and density, the paper's Table 1 in two
blocks (AP@0.5 and AP@0.7 in %, rows = policies, columns = noise levels), then
the pose-error table; a crowding table (AP@0.7 vs density) when the sweep has
several densities; the failed cells with their errors. A sweep with grid axes
(``--grid``: overrides whose value varies) has instead, per scenario, density and the
overrides it keeps, AP@0.5 and AP@0.7 against each axis (one block per noise level and
value of the other axes) and the pose-error table with a column per axis; and a plot of
AP@0.7 against each axis.
"""

from __future__ import annotations

import csv
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from roco_env.sweeps import plots
from roco_env.sweeps.aggregate import SummaryRow, summarize
from roco_env.sweeps.tables import (
    ap_by_axis,
    ap_by_density,
    ap_by_noise,
    axis_label,
    density_label,
    grid_axes,
    noise_label,
    pose_table,
)
from roco_env.sweeps.text_specs import format_scalar


@dataclass
class Report:
    """What was written: the Markdown text and every file path."""

    markdown: str
    files: list[Path]


def _groups(rows: Sequence[SummaryRow], key) -> dict:
    groups: dict = {}
    for row in rows:
        groups.setdefault(key(row), []).append(row)
    return groups


def _short_episodes(rows: Sequence[SummaryRow]) -> str:
    """A sentence naming the settings whose episodes ended before their steps, or ''."""
    short = sorted({(r.scenario, int(r.metrics["steps_played"]), r.steps) for r in rows
                    if r.metrics.get("steps_played", r.steps) < r.steps})
    if not short:
        return ""
    return (" Episodes that ran out of frames ended sooner: " + "; ".join(
        f"{scenario} after {played} of {steps} steps" for scenario, played, steps in short)
        + ".")


def render_markdown(rows: Sequence[SummaryRow], failures: Sequence[dict],
                    title: str = "Policy comparison") -> str:
    """The whole report as Markdown text."""
    parts = [f"# {title}", ""]
    if rows:
        steps = sorted({r.steps for r in rows})
        seeds = sorted({r.seeds + r.failed for r in rows})
        parts += [f"Episodes of {', '.join(map(str, steps))} steps; seeds per setting: "
                  f"{', '.join(map(str, seeds))}. AP = mean over seeds of each episode's dataset "
                  "AP (OpenCOOD protocol); RPE and success pool every collaborator slot of every "
                  "step; noise s/s = sigma_t s m, sigma_r s deg. Warm time per call = median "
                  "wall time of a policy call after each agent's first (which pays one-off "
                  "compilation), mean over seeds." + _short_episodes(rows), ""]
    axes = grid_axes(rows)

    def kept(row: SummaryRow) -> tuple:  # the overrides that are no grid axis
        return tuple((k, v) for k, v in row.overrides.items() if k not in axes)

    for (scenario, density, fixed), group in _groups(
            rows, lambda r: (r.scenario, r.density, kept(r))).items():
        overrides = ", ".join(f"{k}={format_scalar(v)}" for k, v in fixed)
        extra = f"; {overrides}" if overrides else ""
        parts += [f"## {scenario} (density {density_label(density)}{extra})", ""]
        if axes:
            parts += _axis_blocks(group, axes)
        else:
            for key, name in (("ap50", "AP@0.5 (%)"), ("ap70", "AP@0.7 (%)")):
                parts += [f"### {name}", "", ap_by_noise(group, key), ""]
        parts += ["### Relative pose error and success", "", pose_table(group, axes), ""]
    for (scenario, noise), group in _groups(rows, lambda r: (r.scenario, r.noise)).items():
        if len({r.density for r in group}) > 1:
            parts += [f"## Crowding: {scenario}, noise {noise_label(noise)}", "",
                      "### AP@0.7 (%) vs density", "", ap_by_density(group, "ap70"), ""]
    if failures:
        parts += ["## Failed cells", ""]
        parts += [f"- `{f['key']}`: {f.get('error', 'unknown error')}" for f in failures]
        parts.append("")
    return "\n".join(parts)


def _axis_blocks(group: Sequence[SummaryRow], axes: Sequence[str]) -> list[str]:
    """AP@0.5 and AP@0.7 against each grid axis (and the bytes received, with the network
    stage on), a block per noise level and value of the other axes."""
    parts = []
    for axis in axes:
        others = [a for a in axes if a != axis]
        for (noise, *values), members in _groups(group, lambda r, others=others: (
                r.noise, *(axis_label(r.overrides.get(a)) for a in others))).items():
            where = ", ".join([f"noise {noise_label(noise)}",
                               *(f"{a}={v}" for a, v in zip(others, values, strict=True))])
            for key, name in (("ap50", "AP@0.5 (%)"), ("ap70", "AP@0.7 (%)")):
                parts += [f"### {name} vs {axis} ({where})", "", ap_by_axis(members, axis, key),
                          ""]
            if any(math.isfinite(r.metrics.get("bytes_received", math.nan)) for r in members):
                parts += [f"### Bytes received per agent-step vs {axis} ({where})", "",
                          ap_by_axis(members, axis, "bytes_received", 1.0, 0), ""]
    return parts


def _write_csv(rows: Sequence[SummaryRow], path: Path) -> Path:
    flat = [row.flat() for row in rows]
    fields = list(dict.fromkeys(k for item in flat for k in item))
    with path.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=fields)
        writer.writeheader()
        writer.writerows(flat)
    return path


def write_report(records: Sequence[dict], out_dir: str | os.PathLike,
                 title: str = "Policy comparison", with_plots: bool = True) -> Report:
    """Summarise ``records`` (store records of one sweep) and write the report files."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    rows = summarize(records)
    failures = [r for r in records if r["status"] != "ok"]
    markdown = render_markdown(rows, failures, title)
    report_path = out / "report.md"
    report_path.write_text(markdown, encoding="utf-8")
    files = [report_path, _write_csv(rows, out / "summary.csv")]
    ok_rows = [r for r in rows if r.seeds]
    if with_plots and ok_rows:
        files.append(plots.ap_vs_noise(ok_rows, out / "ap70_vs_noise.png"))
        if len({r.density for r in ok_rows if r.density is not None}) > 1:
            files.append(plots.ap_vs_density(ok_rows, out / "ap70_vs_density.png"))
        if any(r.after.size for r in ok_rows):
            files.append(plots.rpe_distribution(ok_rows, out / "rpe_distribution.png"))
        for axis in grid_axes(ok_rows):
            files.append(plots.ap_vs_axis(ok_rows, axis, out / plots.axis_plot_name(axis)))
    return Report(markdown, files)
