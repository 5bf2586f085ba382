"""`controlled-islanding partition`: the paper's tables from the command line, and named errors."""

from __future__ import annotations

import json

import pytest

from controlled_islanding.cli import main

CASE1 = ['--outage', '16-17', '--outage', '1-2', '--group', '30,37,38', '--group', '31,32,33,34,35,36,39']
CASE2 = ['--outage', '13-14', '--outage', '16-17', '--group', '33,34,35,36', '--group', '30,31,32,37,38,39']


def run_json(capsys: pytest.CaptureFixture[str], args: list[str]) -> dict:
    assert main(['partition', '--case', 'ieee39', *args, '--json']) == 0
    return json.loads(capsys.readouterr().out)


def test_case1_json_is_table1(capsys: pytest.CaptureFixture[str]) -> None:
    out = run_json(capsys, CASE1)
    assert out['islands'][0] == [2, 3, 17, 18, 25, 26, 27, 28, 29, 30, 37, 38]
    assert out['cut_lines'] == [[3, 4]] and out['lines_cut'] == 1
    assert out['island_balance'][0]['generation_mw'] == pytest.approx(1620.0)
    assert out['island_balance'][0]['load_mw'] == pytest.approx(1613.5)
    assert out['disrupted_mw'] > 0


@pytest.mark.parametrize('flows', ['pre', 'post'])
def test_case2_json_is_table5(capsys: pytest.CaptureFixture[str], flows: str) -> None:
    # Post-outage flows make moving bus 14 0.4 MW better than Table V, so the paper's method alone is asked for.
    out = run_json(capsys, [*CASE2, '--flows', flows, '--no-refine'])
    assert out['islands'][0] == [15, 16, 19, 20, 21, 22, 23, 24, 33, 34, 35, 36]
    assert out['cut_branch_ids'] == ['14-15']
    assert out['island_balance'][0]['generation_mw'] == pytest.approx(2350.0)
    assert out['island_balance'][0]['load_mw'] == pytest.approx(2159.1)


def test_one_group_is_no_split(capsys: pytest.CaptureFixture[str]) -> None:
    out = run_json(capsys, ['--group', '30,31,32,33,34,35,36,37,38,39'])
    assert not out['split'] and out['cut_lines'] == [] and len(out['islands']) == 1


def test_table_output(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(['partition', *CASE1]) == 0
    text = capsys.readouterr().out
    assert 'island 0: buses 2,3,17,18,25,26,27,28,29,30,37,38' in text
    assert 'open lines (1): 3-4' in text


@pytest.mark.parametrize(('args', 'named'), [
    (['--group', '30,37,38', '--group', '31,32,33,34,35,36,99'], 'bus 99'),
    (['--group', '30,37,38', '--group', '31,32,33,34,35,36,39,38'], 'bus 38 is named by two --group options'),
    (['--outage', '5-9', *CASE1[4:]], "'5-9'"),
    (['--group', '30,37,38', '--group', '31,32,33,34,35,36'], '39 are in no --group'),
    (['--outage', '2-30', *CASE1[4:]], 'not connected'),
    (['--group', '30,37,x'], "'x' is not a bus number"),
    (['--group', '30,4'], 'bus 4 has no generator'),
    (['--case', 'case77', *CASE1], 'case77'),
])
def test_bad_input_is_named(capsys: pytest.CaptureFixture[str], args: list[str], named: str) -> None:
    assert main(['partition', *args]) == 2
    assert named in capsys.readouterr().err


def test_help_teaches(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit):
        main(['partition', '--help'])
    text = capsys.readouterr().out
    assert 'generator' in text and '--group 30,37,38' in text and '16-17' in text
