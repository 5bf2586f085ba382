"""Rotor angle estimation E = V + (ra + j xq) I: conventions, lost samples, and error against simulator truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from controlled_islanding.core.rotor_angle import RotorAngleError, estimate_rotor_angle_rad, unwrap_nan
from controlled_islanding.sim.manifest import manifest_entries

REPO = Path(__file__).resolve().parents[1]


def machine_phasors(delta_rad: np.ndarray, e_pu: float, v_angle_rad: np.ndarray, xq_pu: float, ra_pu: float):
    """Terminal phasors of a machine whose q-axis voltage E = e_pu at angle delta drives current into V = 1 pu."""
    e = e_pu * np.exp(1j * delta_rad)
    v = np.exp(1j * v_angle_rad)
    i = (e - v) / (ra_pu + 1j * xq_pu)  # current leaving the machine
    return np.abs(v), np.angle(v), np.abs(i), np.angle(i)


def test_recovers_a_known_rotor_angle_through_wraps() -> None:
    t = np.linspace(0.0, 4.0, 241)
    delta = 0.6 + 5.0 * t  # several turns: the estimate must unwrap
    v_angle = 0.3 * np.sin(t)
    est = estimate_rotor_angle_rad(*machine_phasors(delta, 1.2, v_angle, xq_pu=0.7, ra_pu=0.003), 0.7, 0.003)
    assert est == pytest.approx(delta - 2 * np.pi * np.round((delta[0] - est[0]) / (2 * np.pi)), abs=1e-9)
    assert np.all(np.diff(est) > 0)


def test_generators_in_columns_with_own_reactances() -> None:
    delta = np.array([[0.2, -0.4], [0.3, -0.5]])
    xq = np.array([0.5, 1.1])
    phasors = [np.empty((2, 2)) for _ in range(4)]
    for g in range(2):
        for k, arr in enumerate(machine_phasors(delta[:, g], 1.1, np.zeros(2), xq[g], 0.0)):
            phasors[k][:, g] = arr
    assert estimate_rotor_angle_rad(*phasors, xq) == pytest.approx(delta, abs=1e-12)


def test_lost_samples_stay_nan_and_do_not_break_unwrapping() -> None:
    angle = np.unwrap(np.linspace(0, 20, 200) % (2 * np.pi) - np.pi)
    wrapped = np.angle(np.exp(1j * angle))
    wrapped[[0, 50, 51, 52, 199]] = np.nan
    out = unwrap_nan(wrapped)
    ok = ~np.isnan(wrapped)
    assert np.isnan(out[~ok]).all()
    assert out[ok] - out[ok][0] == pytest.approx(angle[ok] - angle[ok][0], abs=1e-9)


def test_bad_inputs_are_named() -> None:
    one = np.ones(5)
    with pytest.raises(RotorAngleError, match='share one shape'):
        estimate_rotor_angle_rad(one, one, one, np.ones(4), 0.5)
    with pytest.raises(RotorAngleError, match='xq_pu'):
        estimate_rotor_angle_rad(one, one, one, one, float('nan'))
    with pytest.raises(RotorAngleError, match='xq_pu'):
        estimate_rotor_angle_rad(np.ones((5, 2)), np.ones((5, 2)), np.ones((5, 2)), np.ones((5, 2)), [0.5, 0.5, 0.5])


def _clean_bags() -> list[Path]:
    """Return one bag without impairments per case file (per system and input format)."""
    chosen: dict[str, Path] = {}
    for entry in manifest_entries(REPO / 'bags' / 'index.yaml'):
        case = yaml.safe_load((REPO / 'bags' / entry['scenario']).read_text())['case']
        if not entry.get('impairments') and (REPO / 'bags' / entry['bag']).exists():
            chosen.setdefault(case, REPO / 'bags' / entry['bag'])
    return list(chosen.values())


# Found and not yet explained (issue 11): strict, so a fixed bag fails here until it is taken out.
ROTOR_ANGLE_OFF = {
    'ieee14_g1_unstable': 'GENROU_1 (loads doubled) is 2.2 deg off ANDES at p99 before the fault, over the 1 deg bound',
    'ieee14_psse_g1_borderline': 'GENROU_1 is 2.2 deg off ANDES at p99 before the fault, over the 1 deg bound',
    'ei33_bus101048_pair_unstable': '17 of the 42 GENROU (GENROU_43 and GENROU_68 to _84) are a steady 2.5 to 5 deg '
                                    'off ANDES before the fault, the 42 GENCLS and the other GENROU within 1 deg',
    'nordic44_bus6000_three_groups': 'before the fault (t < 0.5 s) the machines of buses 5300 and 6000 are 1.2 to '
                                     '1.6 deg off ANDES at p99',
}


@pytest.mark.parametrize('path', [pytest.param(p, id=p.name, marks=pytest.mark.xfail(
    strict=True, reason=ROTOR_ANGLE_OFF[p.name])) if p.name in ROTOR_ANGLE_OFF else pytest.param(p, id=p.name)
    for p in _clean_bags()])
def test_error_against_simulator_truth_before_the_fault(path: Path) -> None:
    from controlled_islanding.sim.scenario import load_scenario
    from controlled_islanding.wire.bagdata import load_bag

    bag = load_bag(path)
    scenario = load_scenario(path.parent / f'{path.name}.yaml')
    # A fault cleared without a trip has no branch event: the scenario dates it.
    first_event_s = min([e.t_s for e in bag.branch_events] + [f.start_s for f in scenario.faults]
                        + [t.t_s for t in scenario.trips] + [bag.tag_s[-1]])
    steady = bag.tag_s < first_event_s - 0.5
    for g in bag.grid.generators:
        c = bag.pmu_column(g.name, g.bus)
        est = estimate_rotor_angle_rad(bag.v_mag_pu[:, c], bag.v_angle_rad[:, c], bag.i_mag_pu[:, c],
                                       bag.i_angle_rad[:, c], g.xq_pu, g.ra_pu)
        column = bag.truth_angles_rad[:, bag.truth_generator_names.index(g.name)]
        truth = np.interp(bag.tag_s, bag.truth_t_s, column)
        err = np.abs(np.angle(np.exp(1j * (est - truth))))[steady]
        assert np.nanpercentile(err, 99) < np.radians(1.0), g.name
