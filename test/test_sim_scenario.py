"""Scenario files: every bad field is named, and a failed simulate leaves no bag behind."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from controlled_islanding import cli
from controlled_islanding.sim.scenario import ScenarioError, load_scenario

REPO = Path(__file__).resolve().parents[1]

GOOD = """\
case: ieee39/ieee39_full.xlsx
end_s: 2.0
events:
  - {type: fault, bus: 17, start_s: 1.0, clear_s: 1.1}
  - {type: trip, branch: 16-17, t_s: 1.1}
islanding_request_s: 1.5
"""


def _write(tmp_path: Path, text: str, name: str = 'scn.yaml') -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


def test_good_scenario_defaults(tmp_path: Path) -> None:
    sc = load_scenario(_write(tmp_path, GOOD))
    assert sc.name == 'scn'
    assert sc.rate_fps == 60
    assert sc.pmu_buses is None
    assert sc.case.is_file()
    assert [t.branch for t in sc.trips] == ['16-17']
    assert sc.faults[0].bus == 17


@pytest.mark.parametrize(('change', 'field'), [
    (('t_s: 1.1}', 't_s: 2.5}'), 'events[1].t_s'),
    (('clear_s: 1.1}', 'clear_s: 0.9}'), 'events[0].clear_s'),
    (('ieee39/ieee39_full.xlsx', 'no_such_case.xlsx'), 'case: unknown case file'),
    (('end_s: 2.0', 'end_s: 2.0\npmu: {rate_fps: 50}'), 'pmu.rate_fps'),
    (('end_s: 2.0', 'end_s: 2.0\npmu: {noise_tve: 0.05}'), 'pmu.noise_tve'),
    (('end_s: 2.0', 'end_s: 2.0\nimpairments: {frame_loss_rate: 1.5}'), 'impairments.frame_loss_rate'),
    (('end_s: 2.0', 'end_s: 2.0\nimpairments: {silent_pmu_bus: 30}'), 'silent_from_s together'),
    (('end_s: 2.0', 'end_s: 2.0\nstep: 0.01'), "unknown key(s) ['step']"),
    (('type: trip', 'type: open'), 'events[1].type'),
    (('islanding_request_s: 1.5', 'islanding_request_s: 3'), 'islanding_request_s'),
    (('bus: 17, ', ''), 'exactly one of bus'),
    (('end_s: 2.0', 'end_s: 2.0\ndispatch: case9999'), "dispatch: unknown MATPOWER case 'case9999'"),
    (('end_s: 2.0', 'end_s: 2.0\ndispatch: absent.m'), "dispatch: unknown MATPOWER file 'absent.m'"),
    (('end_s: 2.0', 'end_s: 2.0\naddfile: absent.dyr'), "addfile: unknown case file 'absent.dyr'"),
    (('end_s: 2.0', 'end_s: 2.0\ncase_events: off'), 'case_events: expected one of'),
    (('end_s: 2.0', 'end_s: 2.0\ndisable: IEEEST'), 'disable: expected a list'),
    (('end_s: 2.0', 'end_s: 2.0\ndisable: [{model: IEEEST}]'), 'disable[0]: expected {model'),
    (('end_s: 2.0', 'end_s: 2.0\ndisable: [IEEEST, {model: IEEEST, idx: 1, dev: 2}]'), 'disable[1]: unknown key'),
])
def test_bad_field_is_named(tmp_path: Path, change: tuple[str, str], field: str) -> None:
    assert change[0] in GOOD
    path = _write(tmp_path, GOOD.replace(*change))
    with pytest.raises(ScenarioError) as err:
        load_scenario(path)
    assert field in str(err.value)
    assert str(path) in str(err.value)


def test_missing_file_and_bad_yaml(tmp_path: Path) -> None:
    with pytest.raises(ScenarioError, match='cannot read'):
        load_scenario(tmp_path / 'absent.yaml')
    with pytest.raises(ScenarioError, match='not valid YAML'):
        load_scenario(_write(tmp_path, 'case: [unclosed'))


@pytest.mark.parametrize(('change', 'message'), [
    (('bus: 17', 'bus: 99'), 'events[0].bus: unknown bus 99'),
    (('branch: 16-17', 'branch: 16-18'), "events[1].branch: unknown branch '16-18'"),
    (('end_s: 2.0', 'end_s: 2.0\npmu: {buses: [30, 400]}'), 'pmu.buses: unknown bus 400'),
    (('end_s: 2.0', 'end_s: 2.0\ndisable: [NOSUCHMODEL]'), "disable[0]: 'NOSUCHMODEL' is no model and no device"),
    (('end_s: 2.0', 'end_s: 2.0\ndisable: [IEEEST, {model: TGOV1N, idx: TGOV1N_99}]'),
     'disable[1].idx: TGOV1N has no device'),
    (('end_s: 2.0', 'end_s: 2.0\ndisable: [{model: NOPE, idx: 1}]'), "disable[0].model: the case has no model 'NOPE'"),
])
def test_simulate_rejects_what_the_case_lacks_and_writes_nothing(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                  change: tuple[str, str], message: str) -> None:
    path = _write(tmp_path, GOOD.replace(*change))
    out = tmp_path / 'bag'
    status = cli.main(['simulate', str(path), '--out', str(out), '--quiet'])
    assert status == 2
    assert message in capsys.readouterr().err
    assert sorted(p.name for p in tmp_path.iterdir()) == ['scn.yaml']


def test_matpower_dispatch_replaces_loads_and_generation(tmp_path: Path) -> None:
    from controlled_islanding.core.grid import Grid
    from controlled_islanding.sim.andes_sim import simulate

    text = GOOD.replace('end_s: 2.0', 'end_s: 0.05\ndispatch: case39').replace('islanding_request_s: 1.5',
                                                                            'islanding_request_s: 0.05')
    text = text[:text.index('events:')] + text[text.index('islanding_request_s'):]
    sim = simulate(load_scenario(_write(tmp_path, text)), progress=False)
    matpower = Grid.from_matpower('case39')
    assert sum(ld.p_mw for ld in sim.grid.loads) == pytest.approx(sum(ld.p_mw for ld in matpower.loads))
    by_bus = {g.bus: g.p_mw for g in matpower.generators}
    pv = [g for g in sim.grid.generators if g.bus != 39]  # bus 39 is ANDES' slack: the power flow sets it
    assert [g.p_mw for g in pv] == pytest.approx([by_bus[g.bus] for g in pv])


def test_simulate_refuses_to_overwrite(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _write(tmp_path, GOOD)
    out = tmp_path / 'bag'
    out.mkdir()
    (out / 'keep').write_text('x')
    assert cli.main(['simulate', str(path), '--out', str(out), '--quiet']) == 2
    assert '--force' in capsys.readouterr().err
    assert (out / 'keep').read_text() == 'x'


def _case(tmp_path: Path, body: str, name: str = 'case.yaml') -> Path:
    return _write(tmp_path, body, name)


@pytest.mark.parametrize(('case', 'extra', 'message'), [
    # pjm5bus opens a line at 2 s: once inside the run, the scenario must say what to do with it.
    ('5bus/pjm5bus.xlsx', '', 'case_events: the case has its own events before end_s (Toggle 0 at 2 s)'),
    # EI_33 switches a load at 1 s: a bag records branch changes only.
    ('ei/EI_33.xlsx', 'case_events: keep', 'case_events: keep: Toggle 1 at 1 s does not switch a line'),
])
def test_case_events_inside_the_run_need_a_decision(tmp_path: Path, case: str, extra: str, message: str) -> None:
    from controlled_islanding.sim.andes_sim import simulate

    path = _case(tmp_path, f'case: {case}\n{extra}\nend_s: 3.0\nislanding_request_s: 3.0\n')
    with pytest.raises(ScenarioError) as err:
        simulate(load_scenario(path), progress=False)
    assert message in str(err.value)
    assert str(path) in str(err.value)


def test_disable_takes_devices_out_and_generators_with_them(tmp_path: Path) -> None:
    from controlled_islanding.sim.andes_sim import simulate

    sim = simulate(load_scenario(_case(tmp_path, """\
case: ieee39/ieee39_full.xlsx
disable: [IEEEST, {model: GENROU, idx: [GENROU_2]}, TGOV1_2, IEEEX1_2]
end_s: 0.05
islanding_request_s: 0.05
""")), progress=False)
    assert 'GENROU_2' not in sim.generator_names and len(sim.generator_names) == 9
    assert 'GENROU_2' not in [g.name for g in sim.grid.generators]
    assert sim.delta_rad.shape[1] == 9


def test_loading_cases_leaves_no_andes_log_folder_behind(monkeypatch: pytest.MonkeyPatch) -> None:
    """ANDES' default logger made a new <tmp>/andes-XXXXXXXX folder at every load, never removed."""
    import andes.main

    from controlled_islanding.sim.andes_sim import load_power_flow, prepare_case

    made = []
    monkeypatch.setattr(andes.main, 'get_log_dir', lambda: made.append(1) or '/nonexistent')
    load_power_flow('ieee14/ieee14_full.xlsx')
    prepare_case(load_scenario(REPO / 'bags' / 'kundur_bus9_unstable.yaml'))
    assert made == []


def test_classical_machines_get_xd1_and_kept_case_events_become_branch_changes(tmp_path: Path) -> None:
    import andes

    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad
    from controlled_islanding.sim.andes_sim import simulate
    from controlled_islanding.sim.pmu import measure

    # pjm5bus: four GENCLS; its own Toggle opens the second 0-1 line at 2 s.
    scenario = load_scenario(_case(tmp_path, """\
case: 5bus/pjm5bus.xlsx
case_events: keep
end_s: 2.1
islanding_request_s: 2.1
"""))
    sim = simulate(scenario, progress=False)
    ss = andes.load(andes.get_case('5bus/pjm5bus.xlsx'), no_output=True, default_config=True)
    xd1 = dict(zip((str(n) for n in ss.GENCLS.name.v), ss.GENCLS.xd1.v, strict=True))
    assert [g.xq_pu for g in sim.grid.generators] == pytest.approx([xd1[g.name] for g in sim.grid.generators])
    assert all(g.xq_pu > 0 for g in sim.grid.generators)
    assert sim.case_branch_changes == ((2.0, '0-1#2', False),)
    # With x'd the classical machine's internal voltage angle is its rotor angle.
    pmu = measure(sim, scenario)
    before = pmu.tag_s < 1.9
    est = estimate_rotor_angle_rad(pmu.v_mag_pu[before], pmu.v_angle_rad[before], pmu.i_mag_pu[before],
                                   pmu.i_angle_rad[before], np.array([g.xq_pu for g in sim.grid.generators]),
                                   np.array([g.ra_pu for g in sim.grid.generators]))
    assert np.degrees(np.abs(est - pmu.truth_delta_rad[before])).max() < 1.0


@pytest.mark.xfail(strict=True, reason='found in the last full run: one of the 80 Nordic 44 machines is 2.7 deg off '
                                      'ANDES at steady state with its own channel (bound 0.5 deg), the rest 0.3 deg; '
                                      'not diagnosed (issue 11)')
def test_psse_raw_with_dyr_and_per_machine_current_channels(tmp_path: Path) -> None:
    from controlled_islanding.core.rotor_angle import estimate_rotor_angle_rad
    from controlled_islanding.sim.andes_sim import simulate
    from controlled_islanding.sim.pmu import measure

    # Nordic 44 (PSS/E, SBASE 1000 MVA): 80 machines on 44 buses; its power flow converges only with the lines
    # put on the system base (andes_sim docstring).
    scenario = load_scenario(_case(tmp_path, """\
case: nordic44/N44_BC.raw
addfile: nordic44/N44_BC.dyr
end_s: 0.1
islanding_request_s: 0.1
pmu: {rate_fps: 30, noise_tve: 0.0}
"""))
    sim = simulate(scenario, progress=False)
    assert len(sim.generator_names) == 80
    pmu = measure(sim, scenario)
    shared = {b for b in sim.generator_buses if sim.generator_buses.count(b) > 1}
    assert shared
    for bus in shared:
        gens = [n for n, b in zip(sim.generator_names, sim.generator_buses, strict=True) if b == bus]
        assert sorted(s for s, b in zip(pmu.station_ids, pmu.buses, strict=True) if b == bus) == \
            sorted(f'PMU_{bus}/{n}' for n in gens)
    column = {s: j for j, s in enumerate(pmu.station_ids)}
    errors = []
    for g, (name, bus) in enumerate(zip(sim.generator_names, sim.generator_buses, strict=True)):
        j = column[f'PMU_{bus}/{name}' if bus in shared else f'PMU_{bus}']
        gen = sim.grid.generators[g]
        est = estimate_rotor_angle_rad(pmu.v_mag_pu[:, j], pmu.v_angle_rad[:, j], pmu.i_mag_pu[:, j],
                                       pmu.i_angle_rad[:, j], gen.xq_pu, gen.ra_pu)
        errors.append(np.degrees(np.abs(est - pmu.truth_delta_rad[:, g])).max())
    # A bus-total current was 13 to 18 degrees off; each machine's own current is exact at steady state.
    assert max(errors) < 0.5, max(errors)


def test_a_static_case_is_refused_naming_case(tmp_path: Path) -> None:
    from controlled_islanding.sim.andes_sim import simulate

    with pytest.raises(ScenarioError, match='case: case14.m has no synchronous machine'):
        simulate(load_scenario(_case(tmp_path, """\
case: matpower/case14.m
end_s: 1.0
islanding_request_s: 1.0
""")), progress=False)


# PJM 5-bus, a 100 ms fault at bus 4 cleared by tripping 0-4 (the former pjm5bus_three_groups): ANDES reaches the
# end, but from the clearing buses 3 and 4 sit at 1e-17 pu with their machines in service and no machine carries
# power (measured; clearing the fault alone does not converge).
COLLAPSING = """\
case: 5bus/pjm5bus.xlsx
case_events: disable
end_s: 1.4
events:
  - {type: fault, bus: 4, start_s: 1.0, clear_s: 1.1}
  - {type: trip, branch: 0-4, t_s: 1.1}
islanding_request_s: 1.3
"""


def test_collapsed_at_tells_a_collapse_from_a_fault_and_a_slip():
    from controlled_islanding.sim.andes_sim import COLLAPSED_FOR_S, collapsed_at

    t = np.arange(0.0, 2.0, 0.01)
    v = np.ones((t.size, 3))
    v[(t >= 0.5) & (t <= 0.7), 0] = 1e-3  # a bolted fault
    v[[90, 91], 1] = 0.0  # the electrical centre of a slip passing a terminal
    assert collapsed_at(t, v, [0, 1, 2], [(0.5, 0.7)]) is None
    assert collapsed_at(t, v, [0, 1, 2], []) == (pytest.approx(0.5), [0])  # the same dip with no fault
    v[150:, 2] = -1e-11
    v[150:, 1] = 1e-17
    assert collapsed_at(t, v, [0, 1, 2], [(0.5, 0.7)]) == (pytest.approx(1.5), [1, 2])
    assert collapsed_at(t, v, [0], [(0.5, 0.7)]) is None  # a bus without a machine may be dead
    end = 150 + round(COLLAPSED_FOR_S / 0.01)
    v[150:end, 0] = 0.0
    assert collapsed_at(t[:end], v[:end], [0], [(0.5, 0.7)]) is None  # shorter than COLLAPSED_FOR_S
    v[end, 0] = 0.0
    assert collapsed_at(t[:end + 1], v[:end + 1], [0], [(0.5, 0.7)]) == (pytest.approx(1.5), [0])


def test_a_run_on_a_collapsed_network_is_refused_and_nothing_is_written(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    from controlled_islanding.sim.andes_sim import SimulationError, simulate

    path = _case(tmp_path, COLLAPSING)
    with pytest.raises(SimulationError, match=r'from t = 1\.1\d\d s, with no fault applied, bus\(es\) 3, 4 of '
                                              r'machines in service .* collapsed network'):
        simulate(load_scenario(path), progress=False)
    out = tmp_path / 'bag'
    assert cli.main(['simulate', str(path), '--out', str(out)]) != 0
    assert not out.exists() and 'collapsed network' in capsys.readouterr().err
