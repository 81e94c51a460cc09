"""The gap benchmark's oracle (scripts/gap_benchmark.py): the truth model a case was made
with, in evcal's terms, and the classes its singles are reported by. No simulation: these
check what goes into the oracle's model, which decides whether an effect counts as visible.
"""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest

from evcal.gap.stats import NOMINAL_LOG_OFFSET_DN
from evcal.sim.effects import ApsFpn, Bandwidth, ShotNoise, TimestampQuantisation

SCRIPT = Path(__file__).resolve().parents[1] / "scripts" / "gap_benchmark.py"


@pytest.fixture(scope="module")
def gb() -> ModuleType:
    spec = importlib.util.spec_from_file_location("gap_benchmark_under_test", SCRIPT)
    assert spec is not None
    assert spec.loader is not None
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod
    spec.loader.exec_module(mod)
    return mod


def _case_npz(tmp_path: Path, log_offset: float = 0.0, first_frame_us: int = 230) -> Path:
    h, w = 6, 8
    path = tmp_path / "case.npz"
    np.savez(path, truth_contrast=np.full((h, w), 0.17, np.float32),
             truth_bias=np.full((h, w), -0.02, np.float32),
             truth_log_offset=np.full((h, w), log_offset, np.float32),
             frame_t_us=np.array([first_frame_us, first_frame_us + 40000], np.int64))
    return path


V2E_TRUTH = {
    "hidden": ["bandwidth", "shot_noise"], "median_dn": 110.0,
    "effects": [
        # as scripts/gapbench_v2e_worker.py writes them: notes evcal's effects do not take
        {"name": "bandwidth", "parameters": {"cutoff_hz": 60.0, "ref_dn": 128.0,
                                             "law": "v2e: cutoff_hz (I + 20) / 275"}},
        {"name": "shot_noise", "parameters": {"rate_at_median_hz": 2.0, "threshold_factor": 1.01,
                                              "law": "v2e: ..."}},
    ]}


def test_a_v2e_truth_keeps_every_effect_and_gets_v2e_stamps(gb: ModuleType,
                                                            tmp_path: Path) -> None:
    model = gb.truth_model(_case_npz(tmp_path), V2E_TRUTH, backend="v2e")
    bw = model.effects["bandwidth"]
    assert isinstance(bw, Bandwidth)
    assert bw.cutoff_hz == 60.0
    shot = model.effects["shot_noise"]
    assert isinstance(shot, ShotNoise)
    # the rate at the scene's median light is the truth's, and the power law's slope there is
    # that of v2e's law, linear in light: rate ~ 1 - 0.75 (I + 20) / 275
    assert float(shot.rate_at(np.asarray(110.0))) == pytest.approx(2.0, rel=1e-9)
    law = lambda i: 1.0 - 0.75 * (i + 20.0) / 275.0  # noqa: E731
    slope = (np.log(law(111.0)) - np.log(law(109.0))) / (np.log(111.0) - np.log(109.0))
    assert shot.light_exponent == pytest.approx(-slope, rel=1e-3)
    q = model.effects["timestamp_quantisation"]
    assert isinstance(q, TimestampQuantisation)
    assert (q.step_us, q.scheme) == (500.0, "spread")
    # v2e's steps end on the absolute 500 us grid; the phase counts from the first frame
    assert (230 + q.phase_us) % 500 == 0


def test_a_left_out_effect_is_gone_and_nothing_else(gb: ModuleType, tmp_path: Path) -> None:
    npz = _case_npz(tmp_path)
    model = gb.truth_model(npz, V2E_TRUTH, backend="v2e", drop="bandwidth",
                           add=("start_reset",))
    assert set(model.effects) == {"shot_noise", "timestamp_quantisation", "start_reset"}
    sim = gb.truth_model(npz, V2E_TRUTH, backend="sim")
    assert "timestamp_quantisation" not in sim.effects


def test_a_dark_level_left_out_leaves_the_nominal_offset(gb: ModuleType,
                                                         tmp_path: Path) -> None:
    # a sim case's maps carry the dark level it hid: leaving the effect out must take it out
    # of the maps' offset too, or the model without it still has it
    npz = _case_npz(tmp_path, log_offset=29.0)
    truth = {"hidden": ["log_offset"], "median_dn": 80.0,
             "effects": [{"name": "log_offset", "parameters": {"dark_dn": 29.0}}]}
    with_it = gb.truth_model(npz, truth)
    without = gb.truth_model(npz, truth, drop="log_offset")
    assert with_it.log_offset == 29.0
    assert "log_offset" in with_it.effects
    assert without.log_offset == NOMINAL_LOG_OFFSET_DN
    assert not without.effects


def test_the_frames_dark_offsets_are_the_drawn_map(gb: ModuleType, tmp_path: Path) -> None:
    # the gap model corrects the frames only by a known map: the truth's is the drawn one
    truth = {"hidden": ["aps_fpn"], "median_dn": 80.0,
             "effects": [{"name": "aps_fpn",
                          "parameters": {"sigma_dn": 4.0, "mean_dn": 0.0, "seed": 12345}}]}
    fpn = gb.truth_model(_case_npz(tmp_path), truth).effects["aps_fpn"]
    assert isinstance(fpn, ApsFpn)
    assert fpn.offset_dn is not None
    drawn = ApsFpn(sigma_dn=4.0, mean_dn=0.0, seed=12345).offsets_dn((6, 8))
    np.testing.assert_array_equal(fpn.offset_dn, drawn)


def test_singles_are_classed_by_what_their_truth_shows(gb: ModuleType) -> None:
    def case(gap: float, visible: bool, named: list[str]) -> dict[str, object]:
        return {"category": "single", "hidden": ["leak"], "named": named,
                "oracle": {"gap_truth": gap, "effects": {"leak": {"visible": visible}}}}

    cases = [case(1.2, True, ["leak"]), case(1.5, True, []), case(0.8, False, []),
             case(9.0, True, ["shot_noise"])]
    assert [gb.oracle_class(c) for c in cases] == [
        "reproduced, visible", "reproduced, visible", "reproduced, not visible",
        "not reproduced"]
    classes = gb.oracle_classes(cases)
    assert classes["reproduced, visible"][:2] == [2, "50%"]
    assert gb.oracle_class({"category": "single", "hidden": ["leak"], "named": []}) is None


def test_a_flickering_light_is_in_the_truth_on_the_same_time_base(gb: ModuleType,
                                                                  tmp_path: Path) -> None:
    # the frames cannot show a mains flicker, so a truth without it is not the case's model;
    # its factor must be the generator's light at the same (the recording's) times
    ill = {"kind": "flicker", "freq_hz": 120.0, "depth": 0.07, "phase_rad": 2.5}
    npz = _case_npz(tmp_path)
    model = gb.truth_model(npz, {"hidden": [], "median_dn": 80.0, "effects": []},
                           illumination=ill)
    fl = model.effects["flicker"]
    t_s = np.linspace(0.0, 3.0, 997)
    np.testing.assert_allclose(fl.on_light(t_s), gb.gs.illumination_gain(ill, t_s, 3.0),
                               rtol=1e-12)
    assert "flicker" not in gb.truth_model(npz, {"hidden": [], "median_dn": 80.0,
                                                 "effects": []}, illumination=ill,
                                           drop="flicker").effects
    steady = {"kind": "sine", "freq_hz": 1.0, "depth": 0.2, "phase_rad": 0.0}
    assert "flicker" not in gb.truth_model(npz, {"hidden": [], "median_dn": 80.0,
                                                 "effects": []}, illumination=steady).effects
