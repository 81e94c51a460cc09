"""Outputs of the gap workflow: ``report.json`` (stable schema), ``report.md`` with PNG plots.

matplotlib is imported only when plots are written (it is an optional dependency).
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np

from ..jsonable import dumps, to_jsonable
from . import effects as registry
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
        "pairs_tried": to_jsonable(result.pairs_tried),
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
    motion = info.get("subframe_motion")
    if motion:
        lines += [f"Motion between frames read from the events (the light off the flow's "
                  f"straight path, `--no-subframe-motion` to leave it): in "
                  f"{motion['kept']:.0f} of {motion['intervals']:.0f} frame intervals, "
                  f"{motion['rms_px']:.2f} px RMS.", ""]
    named = result.named_effects
    lines += [f"**Named effects** (in the order added): {', '.join(named) if named else 'none'}",
              "", f"Gap (mean standardised discrepancy, about 1 when the model explains the "
              f"data): {result.initial.gap:.2f} initially, {result.final.gap:.2f} finally.", ""]
    if result.steps:
        lines += ["| step | effect | what it is | gap before | gap after | held-out gap | "
                  "moved statistics | worsened |", "|---|---|---|---|---|---|---|---|"]
        for i, s in enumerate(result.steps, 1):
            words = registry.spec(s.effect.name).says(s.effect)
            lines.append(f"| {i} | {s.effect.name} | {words} | {s.before.gap:.2f} | "
                         f"{s.after.gap:.2f} | {s.before.held_gap:.2f} -> "
                         f"{s.after.held_gap:.2f} | {', '.join(s.moved_statistics())} | "
                         f"{', '.join(s.worsened_statistics()) or '-'} |")
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
            lines += [f"### Step {i}: {s.effect.name}", ""]
            lines += _why_lines(s.effect.name, s.why)
            lines += ["Candidates (held-out gap with the candidate added, those judged on "
                      "every seed first; the fitter's reason where it saw none):", ""]
            lines += _candidate_lines(s.candidates)
            lines.append("")
    if result.dropped:
        lines += ["## Taken out again", "",
                  "Effects named in a round and dropped from the final model: without them the "
                  "held-out gap rises by less than naming needs (what was named after them "
                  "explains the same):", ""]
        for d in result.dropped:
            params = ", ".join(f"{k}={v}" for k, v in d["parameters"].items())
            lines.append(f"- {d['effect']} ({params}), named in step {d['named_in_step']}: "
                         f"held-out gap {d['held_out_gap_with']:.2f} with it, "
                         f"{d['held_out_gap_without']:.2f} without (naming needs "
                         f"{d['needed_gain']:.2f})")
        lines.append("")
    lines += ["## Why the search stopped", "",
              "Candidates of the last round (none gained enough on the held-out rows to be "
              "named):" if result.rejected else "The largest number of effects was named.",
              ""]
    lines += _candidate_lines(result.rejected)
    lines.append("")
    if result.pairs_tried:
        lines += ["Pairs of two effects tried (the second fitted on top of the first; "
                  "held-out gap with both):", ""]
        for p in result.pairs_tried:
            why = p.get("why", {})
            tail = f": not named, {why['reason']}" if why.get("reason") else ""
            lines.append(f"- {' + '.join(p['pair'])} ({p['status']}): held-out gap "
                         f"{p.get('held_out_gap', float('nan')):.2f}{tail}")
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


def _why_lines(name: str, why: dict[str, Any]) -> list[str]:
    """Why a step's effect was named, in a sentence or two."""
    if "held_out_gain" not in why:
        if why.get("alone") is not None:
            how = "alone" if why.get("alone") else "with the best sensor candidate"
            return [f"Named because it closes the gap {how} (a simulator's timestamp "
                    "scheme, reported apart).", ""]
        return []
    if why.get("pair"):
        other = [n for n in why["pair"] if n != name]
        text = (f"Named as a pair with {', '.join(other)} (no single effect was enough; "
                f"each of the two adds what naming a single needs to the other alone): "
                f"together they lower the held-out gap from {why['held_out_gap']:.2f} to "
                f"{why['score']:.2f} (with their complexity penalties), a gain of "
                f"{why['held_out_gain']:.2f} where {why['needed_gain']:.2f} was needed")
    else:
        text = (f"Named: it lowers the held-out gap from {why['held_out_gap']:.2f} to "
                f"{why['score']:.2f} (with its complexity penalty), a gain of "
                f"{why['held_out_gain']:.2f} where {why['needed_gain']:.2f} was needed")
    if why.get("null_gain", 0.0) > 0:
        text += f" plus {why['null_gain']:.2f}, what it gains with nothing missing"
    if why.get("scene"):
        text += (" (the scene's light, not the sensor: tried before the sensor's effects, "
                 "and again after each one named)")
    if why.get("start"):
        text += (" (how the recording began, not the sensor: tried before the sensor's "
                 "effects, and again after each one named)")
    below = [f"{o['effect']} ({o['score']:.2f})" for o in why.get("ranked_below", [])]
    if below:
        text += "; it ranked above " + ", ".join(below)
    out = [text + ".", ""]
    if why.get("equivalent"):
        out += [f"Explains the data as well (within the comparison's noise): "
                f"{', '.join(why['equivalent'])}. These effects leave similar signatures on "
                "this recording; a recording with a wider range of light or motion tells them "
                "apart.", ""]
    return out


# the order candidates are listed in: those judged on every seed and the whole sensor
# first (their held-out gaps compare), then those screened on one seed (on a band of rows
# when the recording is large: their gaps are the band's), then those without a simulation
_ORDER = {"named": 0, "confirmed": 0, "not named": 0, "screened": 1}


def _candidate_lines(cands: dict[str, dict[str, Any]]) -> list[str]:
    """The candidates, best first within each kind of judgement (:data:`_ORDER`)."""
    def key(item: tuple[str, dict[str, Any]]) -> tuple[int, float]:
        c = item[1]
        rank = _ORDER.get(c.get("status", ""), 2) if "held_out_gap" in c else 3
        return rank, float(c.get("score", c.get("held_out_gap", 0.0)))

    out = []
    for name, c in sorted(cands.items(), key=key):
        status = c.get("status", "")
        if "held_out_gap" in c:
            params = ", ".join(f"{k}={v}" for k, v in (c.get("parameters") or {}).items())
            how = " (one seed, screening: not comparable with those judged on every seed)" \
                if status == "screened" else ""
            out.append(f"- {name} ({status}): held-out gap {c['held_out_gap']:.2f}{how}, "
                       f"{params}")
        else:
            out.append(f"- {name} ({status}): {c.get('reason', '')}")
    return out


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
