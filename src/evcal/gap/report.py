"""Outputs of the gap workflow: ``report.json`` (stable schema), ``report.md`` with PNG plots.

matplotlib is imported only when plots are written (it is an optional dependency).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..jsonable import dumps, to_jsonable
from .explain import summary
from .workflow import Evaluation, GapResult


def write_json(result: GapResult, out_dir: Path) -> Path:
    path = out_dir / "report.json"
    path.write_text(json.dumps(result.to_json(), indent=2) + "\n", encoding="utf-8")
    return path


def write_details(result: GapResult, out_dir: Path) -> Path:
    """``details.json``: what report.json leaves out (where each statistic differs most,
    every candidate tried at every step, settings)."""
    def where(ev: Evaluation) -> dict[str, Any]:
        return {k: {"discrepancy": ev.disc.per_stat[k], "largest_at": ev.disc.where(k),
                    "labels": ev.disc.labels[k], "z": [float(x) for x in ev.disc.z[k]]}
                for k in ev.disc.per_stat}

    d = {
        "recording": result.recording_info,
        "settings": result.settings,
        "initial": where(result.initial),
        "final": where(result.final),
        "steps": [{"effect": s.effect.name, "candidates": to_jsonable(s.candidates),
                   "after": where(s.after)} for s in result.steps],
        "rejected_candidates": to_jsonable(result.rejected),
    }
    path = out_dir / "details.json"
    path.write_text(dumps(d, indent=2, sort_keys=False) + "\n", encoding="utf-8")
    return path


def _plot_stats(evals: list[tuple[str, Evaluation]], measured: dict[str, np.ndarray],
                path: Path, title: str) -> None:
    import matplotlib  # noqa: PLC0415 - optional, heavy

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # noqa: PLC0415

    names = list(measured)
    ncol = 4
    nrow = int(np.ceil(len(names) / ncol))
    fig, axes = plt.subplots(nrow, ncol, figsize=(4.2 * ncol, 2.8 * nrow), squeeze=False)
    for ax, name in zip(axes.ravel(), names, strict=False):
        m = np.asarray(measured[name])
        x = np.arange(m.size)
        ax.plot(x, m, "ko-", label="measured", lw=1.5, ms=3)
        for (label, ev), col in zip(evals, ("tab:red", "tab:blue", "tab:green"), strict=False):
            mu, sd = ev.disc.sim_mean[name], ev.disc.sim_std[name]
            ax.errorbar(x, mu, yerr=2 * sd, color=col, marker=".", lw=1, capsize=2,
                        label=f"{label} (D={ev.disc.per_stat[name]:.1f})")
        ax.set_title(name, fontsize=9)
        ax.tick_params(labelsize=7)
        ax.legend(fontsize=6)
    for ax in axes.ravel()[len(names):]:
        ax.axis("off")
    fig.suptitle(title, fontsize=11)
    fig.tight_layout()
    fig.savefig(path, dpi=80)
    plt.close(fig)


def write_markdown(result: GapResult, out_dir: Path, *, plots: bool = True) -> Path:
    lines = ["# Model gap report", ""]
    info = result.recording_info
    lines += [f"Recording: {info.get('source', '')} — sensor {info['sensor']}, "
              f"{info['n_events']} events, {info['n_frames']} frames, "
              f"{info['duration_s']:.2f} s.", ""]
    win = info.get("window") or {}
    if win.get("cut"):
        lines += [f"Analysed: its busiest {win['frames']} of {win['of_frames']} frames "
                  f"({win['events']} of {win['of_events']} events; `--max-events`, "
                  "`--max-pixel-steps`).", ""]
    named = result.named_effects
    lines += [f"**Named effects** (in the order added): {', '.join(named) if named else 'none'}",
              "", f"Gap (mean standardised discrepancy, about 1 when the model explains the "
              f"data): {result.initial.gap:.2f} initially, {result.final.gap:.2f} finally.", ""]
    if result.steps:
        lines += ["| step | effect | parameters | gap before | gap after | moved statistics |",
                  "|---|---|---|---|---|---|"]
        for i, s in enumerate(result.steps, 1):
            params = ", ".join(f"{k}={v}" for k, v in s.effect.parameters().items())
            lines.append(f"| {i} | {s.effect.name} | {params} | {s.before.gap:.2f} | "
                         f"{s.after.gap:.2f} | {', '.join(s.moved_statistics())} |")
        lines.append("")
        refits = [s for s in result.steps if s.refit is not None]
        if refits:
            lines += ["Refitted in the final model (an effect named before others is "
                      "searched again once they are in; the table gives the values kept):", ""]
            for s in refits:
                r = s.refit
                assert r is not None
                now = s.effect.parameters()[r["parameter"]]
                what = "kept" if now == r["named_value"] else f"-> {now}"
                lines.append(f"- {s.effect.name} {r['parameter']} {r['named_value']} {what} "
                             f"(final gap {r['gap_before']:.2f} -> {r['gap_after']:.2f})")
            lines.append("")
        for i, s in enumerate(result.steps, 1):
            lines += [f"Candidates at step {i} (gap with the candidate added; — : the data "
                      "show none of it):", ""]
            for name, c in s.candidates.items():
                g = c.get("gap")
                lines.append(f"- {name}: " + ("—" if g is None else
                                               f"gap {g:.2f}, parameters {c['parameters']}"))
            lines.append("")
    if result.rejected:
        lines += ["Candidates of the last round, none of which lowered the gap enough to be "
                  "named (gap with the candidate; — : the data show none of it):", ""]
        for name, c in result.rejected.items():
            g = c.get("gap")
            lines.append(f"- {name}: " + ("—" if g is None else
                                           f"gap {g:.2f}, parameters {c['parameters']}"))
        lines.append("")
    lines += ["## Statistics", "", "| statistic | D initial | D final | largest at (initial) |",
              "|---|---|---|---|"]
    for k in result.initial.disc.per_stat:
        lines.append(f"| {k} | {result.initial.disc.per_stat[k]:.2f} | "
                     f"{result.final.disc.per_stat[k]:.2f} | {result.initial.disc.where(k)} |")
    lines.append("")
    if plots:
        evs = [("base", result.initial)]
        _plot_stats(evs, result.initial.disc.measured, out_dir / "stats_initial.png",
                    "base model")
        lines += ["![statistics, base model](stats_initial.png)", ""]
        prev = result.initial
        for i, s in enumerate(result.steps, 1):
            png = f"stats_step{i}_{s.effect.name}.png"
            _plot_stats([("before", prev), (f"+ {s.effect.name}", s.after)],
                        result.initial.disc.measured, out_dir / png,
                        f"step {i}: + {s.effect.name}")
            lines += [f"![step {i}]({png})", ""]
            prev = s.after
    lines += ["Error bars: 2 standard deviations over the simulation seeds. D: mean squared "
              "standardised discrepancy of the statistic's components.", ""]
    lines += ["## What the model does not explain", "",
              "Where the final model and the measurement still disagree (each statistic's "
              "worst component; measured vs simulated):", ""]
    lines += [f"- {line}" for line in summary(result.final.disc)]
    lines.append("")
    path = out_dir / "report.md"
    path.write_text("\n".join(lines), encoding="utf-8")
    return path


def write_reports(result: GapResult, out_dir: str | Path, *, plots: bool = True,
                  rrd: bool = True) -> dict[str, Path]:
    """Write report.json, details.json, report.md (+ PNGs) and gap.rrd into ``out_dir``."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = {"json": write_json(result, out), "details": write_details(result, out),
             "markdown": write_markdown(result, out, plots=plots)}
    if rrd:
        from .rrd import write_rrd  # noqa: PLC0415 - rerun is optional

        paths["rrd"] = write_rrd(result, out / "gap.rrd")
    return paths
