"""``gap.rrd``: the gap report as a Rerun recording (the only module here importing rerun).

Timeline ``step`` (0 = base model, then one per named effect). Per statistic:
``stats/<name>/measured`` and ``stats/<name>/simulated`` bar charts, ``discrepancy/<name>``
and ``gap`` scalars, and the report text at ``report``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from .workflow import GapResult


def write_rrd(result: GapResult, path: str | Path) -> Path:
    import rerun as rr  # noqa: PLC0415 - optional dependency

    path = Path(path)
    rec = rr.RecordingStream("evcal_gap")
    rec.save(str(path))
    evals = [("base model", result.initial)] + [(f"+ {s.effect.name}", s.after)
                                                for s in result.steps]
    measured = result.initial.disc.measured
    for i, (label, ev) in enumerate(evals):
        rec.set_time("step", sequence=i)
        rec.log("gap", rr.Scalars(float(ev.gap)))
        rec.log("model", rr.TextLog(f"step {i}: {label}, gap {ev.gap:.2f}"))
        for name, m in measured.items():
            if i == 0:
                rec.log(f"stats/{name}/measured",
                        rr.BarChart(np.nan_to_num(np.asarray(m, np.float64))))
            rec.log(f"stats/{name}/simulated", rr.BarChart(np.nan_to_num(
                np.asarray(ev.disc.sim_mean[name], np.float64))))
            rec.log(f"discrepancy/{name}", rr.Scalars(float(ev.disc.per_stat[name])))
    named = ", ".join(result.named_effects) or "none"
    rec.log("report", rr.TextDocument(
        f"# Model gap\n\nnamed effects: {named}\n\ngap {result.initial.gap:.2f} -> "
        f"{result.final.gap:.2f}\n", media_type=rr.MediaType.MARKDOWN), static=True)
    rec.flush()
    rec.disconnect()
    return path
