"""`evaluate --observability`: PMU coverage sweeps on real bags, scored against the truth and the MILP."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from controlled_islanding.evaluation import coherency_rules as study
from controlled_islanding.evaluation import observability_sweep as obs
from controlled_islanding.evaluation.cases import manifest_entry as _manifest_entry
from controlled_islanding.wire.bagdata import load_bag

BAGS = Path(__file__).resolve().parents[1] / 'bags'


@pytest.mark.parametrize('name', ['ieee14_g1_unstable', 'ieee39_case2_g3_unstable'])
def test_sweep_scores_every_draw_against_truth_and_optimum(name, tmp_path):
    bag = load_bag(BAGS / name)
    scenario = study.scenario_from_bag(bag, _manifest_entry(bag))
    grid = bag.grid_at(scenario.request_s + 1e-9)
    rows = obs.sweep(scenario, grid, coverages=(1.0, 0.5), draws=2, seed=1, k_rule='separation',
                     dtw_band=30, time_limit_s=20)
    assert [(r.placement, r.coverage, len(r.draws)) for r in rows] == [
        ('largest machines', 1.0, 1), ('largest machines', 0.5, 1), ('random', 0.5, 2)]
    n = len(grid.generators)
    for row in rows:
        for d in row.draws:
            assert len(d.observed) == max(1, round(row.coverage * n))
            assert not d.error, d.error
            # The MILP is the optimum under the same groups: nothing the spectral clustering finds beats it.
            assert d.gap_pct is None or d.gap_pct >= -1e-6
            # The portfolio keeps the lower of the spectral cut and the exact one: never above either.
            assert d.portfolio_mw is not None and d.portfolio_mw <= d.disrupted_mw + 1e-6
            assert d.portfolio_gap_pct is None or abs(d.portfolio_gap_pct) <= 1e-3
    full = rows[0].draws[0]
    truth_blocks = study.blocks(scenario.truth)
    assert full.groups_right == (full.k == len(truth_blocks))
    page = obs.write_report(rows, tmp_path / 'o.md', command='test', k_rule='separation', window_s=3.0)
    text = page.read_text()
    assert text.count(f'| {name} |') == len(rows) and not list(tmp_path.glob('.*partial'))
    assert f'- {name}: groups ' in text and 'portfolio meets' in text


def test_bad_sweep_settings_are_named():
    bag = load_bag(BAGS / 'ieee14_g1_unstable')
    scenario = study.scenario_from_bag(bag, _manifest_entry(bag))
    with pytest.raises(obs.SweepError, match='coverages'):
        obs.sweep(scenario, bag.grid, coverages=(0.0,), k_rule='separation')
    with pytest.raises(obs.SweepError, match='draws'):
        obs.sweep(scenario, bag.grid, draws=0, k_rule='separation')


def test_half_the_pmus_on_the_two_borderline_requests():
    # PSS/E IEEE 14: G1 and G2 observed, G1 107 deg from G2 and accelerating since clearing 150 ms before the
    # request: a runaway, which the runaway test read as slowing down while it compared with the fault-on motion.
    bag = load_bag(BAGS / 'ieee14_psse_g1_borderline')
    scenario = study.scenario_from_bag(bag, _manifest_entry(bag))
    observed = obs.largest_first(bag.grid_at(scenario.request_s + 1e-9), 0.5)
    row = {n: i for i, n in enumerate(scenario.generator_names)}
    seen = replace(scenario, generator_names=observed, angles_rad=scenario.angles_rad[[row[n] for n in observed]])
    groups = study.groups_at(seen, scenario.request_s, rule='separation', window_s=3.0, max_groups=8, dtw_band=30)
    assert study.blocks(groups) == study.blocks({n: scenario.truth[n] for n in observed})
    assert len(set(groups.values())) == 2
    # Kundur: G1 and G4 observed, 86 deg apart at the request (the frame at which the farthest pair, G1 and G3,
    # first passes 90 deg), below the runaway test's pi / 2; right one frame later, well before the slip.
    bag = load_bag(BAGS / 'kundur_bus9_unstable')
    scenario = study.scenario_from_bag(bag, _manifest_entry(bag))
    observed = obs.largest_first(bag.grid_at(scenario.request_s + 1e-9), 0.5)
    assert observed == ['GENROU_1', 'GENROU_4']
    later = obs.first_right_s(scenario, observed, window_s=3.0, max_groups=8, k_rule='separation', dtw_band=30)
    frame_s = float(np.median(np.diff(scenario.t_s)))
    assert later == pytest.approx(scenario.request_s + frame_s, abs=1e-3) and later < scenario.first_pole_slip_s
