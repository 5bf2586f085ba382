"""The breaker rules of controlled_islanding.safety.actuation, on six ANDES systems (no rclpy, no processes)."""

from __future__ import annotations

import pytest
from breaker_cases import ANDES_CASES, andes_grid, boundary, two_islands

from controlled_islanding.safety.actuation import Refusal, plan_commands

pytestmark = pytest.mark.slow  # loading the six ANDES cases and their power flows takes ~12 s once


@pytest.fixture(scope='module', params=sorted(ANDES_CASES))
def case(request):
    grid = andes_grid(request.param)
    island = two_islands(grid)
    cut = boundary(grid, island)
    assert cut, f'{request.param}: the test split cuts nothing'
    return grid, island, cut


def plan(grid, island, entries, **kwargs):
    kwargs.setdefault('max_breakers', 10_000)
    buses = sorted(island)
    return plan_commands(grid, buses, [island[b] for b in buses], [e[0] for e in entries], [e[1] for e in entries],
                         [e[2] for e in entries], **kwargs)


def entries(cut):
    return [(b.branch_id, b.from_bus, b.to_bus) for b in cut]


def refused(reason, *args, **kwargs):
    with pytest.raises(Refusal) as info:
        plan(*args, **kwargs)
    assert info.value.reason == reason, str(info.value)
    return str(info.value)


def test_exact_boundary_gives_one_command_per_breaker_named_from_the_data(case):
    grid, island, cut = case
    result = plan(grid, island, entries(cut))
    assert sorted(c.branch_id for c in result.commands) == sorted(b.branch_id for b in cut)
    assert [c.breaker_id for c in result.commands] == [f'CB-{c.branch_id}' for c in result.commands]
    assert result.n_islands == 2


def test_duplicates_and_the_other_spelling_are_one_breaker(case):
    grid, island, cut = case
    pairs = {}
    for b in grid.branches:
        pairs.setdefault(frozenset((b.from_bus, b.to_bus)), []).append(b)
    reversed_ok = [b for b in cut if len(pairs[frozenset((b.from_bus, b.to_bus))]) == 1]
    spelled = [(f'{b.to_bus}-{b.from_bus}', b.to_bus, b.from_bus) for b in reversed_ok]
    result = plan(grid, island, entries(cut) * 5 + spelled)
    assert len(result.commands) == len({c.breaker_id for c in result.commands}) == len(cut)
    assert result.merged_entries == 4 * len(cut) + len(spelled)


def test_cut_must_be_exactly_the_boundary(case):
    grid, island, cut = case
    if len(cut) > 1:
        refused('inconsistent_cut', grid, island, entries(cut[1:]))
    inner = next(b for b in grid.branches if b.in_service and island[b.from_bus] == island[b.to_bus])
    refused('inconsistent_cut', grid, island, entries(cut) + entries([inner]))


def test_unknown_and_mislabelled_branches(case):
    grid, island, cut = case
    ghost = max(grid.buses) + 1
    refused('unknown_branch', grid, island, entries(cut) + [(f'{ghost}-{ghost + 1}', ghost, ghost + 1)])
    b = cut[0]
    refused('inconsistent_cut', grid, island, [(b.branch_id, b.from_bus, ghost)] + entries(cut[1:]))


def test_branch_already_out_of_service_or_already_opened(case):
    grid, island, cut = case
    tripped = grid.with_outages([cut[0].branch_id])
    refused('branch_out_of_service', tripped, island, entries(cut))
    refused('branch_out_of_service', grid, island, entries(cut), open_breakers={cut[0].breaker})


def test_island_map_must_cover_exactly_the_network(case):
    grid, island, cut = case
    partial = dict(island)
    partial.pop(next(iter(partial)))
    refused('inconsistent_islands', grid, partial, entries(cut))
    refused('inconsistent_islands', grid, {**island, max(grid.buses) + 7: 0}, entries(cut))
    refused('inconsistent_islands', grid, dict.fromkeys(island, 0), [])


def test_every_island_holds_generation(case):
    grid, island, cut = case
    gen_buses = {g.bus for g in grid.generators if g.p_max_mw > 0}
    lonely = next(b for b in grid.buses if b not in gen_buses)
    three = {**island, lonely: 2}
    refused('island_without_generation', grid, three, entries(boundary(grid, three)))
    # The 'cut everything' decision: one island per bus blacks out every bus without a generator.
    each = {b: i for i, b in enumerate(grid.buses)}
    refused('island_without_generation', grid, each, entries(boundary(grid, each)))


def test_breaker_cap(case):
    grid, island, cut = case
    message = refused('too_many_breakers', grid, island, entries(cut), max_breakers=len(cut) - 1) \
        if len(cut) > 1 else None
    assert message is None or 'max_breakers' in message
    refused('too_large', grid, island, entries(cut) * (2 * len(grid.branches) // len(cut) + 1), max_breakers=len(cut))


def test_mapping_file_overrides_the_snapshot(case):
    grid, island, cut = case
    override = {cut[0].branch_id: 'FIELD-BREAKER-7'}
    result = plan(grid, island, entries(cut), breaker_override=override)
    assert 'FIELD-BREAKER-7' in {c.breaker_id for c in result.commands}
