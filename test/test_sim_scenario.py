"""Scenario files: every bad field is named, and a failed simulate leaves no bag behind."""

from __future__ import annotations

from pathlib import Path

import pytest

from controlled_islanding import cli
from controlled_islanding.sim.scenario import ScenarioError, load_scenario

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
