"""The breaker rules of controlled_islanding.safety.actuation (cut and remedial actions) on six ANDES systems."""

from __future__ import annotations

import pytest
from breaker_cases import ANDES_CASES, andes_grid, boundary, two_islands

from controlled_islanding.core.remedial import bus_load_mw, remedial_actions
from controlled_islanding.safety.actuation import Refusal, plan_actions, plan_commands

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


# --- remedial actions (plan_actions) -------------------------------------------------------------------------------
def actions_of(grid, island, sheds=None, trips=None, **kwargs):
    kwargs.setdefault('max_actions', 10_000)
    buses = sorted(island)
    rule = remedial_actions(grid, island)
    shed = rule.shed_by_bus if sheds is None else sheds
    return plan_actions(grid, buses, [island[b] for b in buses], list(shed), list(shed.values()),
                        list(rule.trip_generators if trips is None else trips), **kwargs)


def refused_actions(reason, *args, **kwargs):
    with pytest.raises(Refusal) as info:
        actions_of(*args, **kwargs)
    assert info.value.reason == reason, str(info.value)
    return str(info.value)


def test_the_rule_actions_pass_each_once_with_their_devices(case):
    grid, island, _ = case
    rule = remedial_actions(grid, island)
    actions = actions_of(grid, island)
    assert [(a.bus, a.amount_mw) for a in actions if a.kind == 'shed'] == list(rule.shed_by_bus.items())
    assert [a.generator for a in actions if a.kind == 'trip'] == list(rule.trip_generators)
    assert all(a.device_id == (f'LS-{a.bus}' if a.kind == 'shed' else f'GCB-{a.generator}') for a in actions)
    # After they were carried out, only what is left of each bus's load can still be shed, and no machine tripped
    # again: no action runs twice.
    done = {a.bus: a.amount_mw for a in actions if a.kind == 'shed'}
    if done:
        left = {b: bus_load_mw(grid)[b] - mw for b, mw in done.items()}
        actions_of(grid, island, shed_before_mw=done, sheds={b: mw for b, mw in left.items() if mw > 1e-6}, trips=[])
        refused_actions('shed_beyond_load', grid, island, shed_before_mw=done, trips=[],
                        sheds={b: mw + 1e-3 for b, mw in left.items()})
    if rule.trip_generators:
        refused_actions('generator_already_tripped', grid, island, tripped_before={rule.trip_generators[0]: 'd0'})


def test_each_action_names_a_load_or_machine_of_the_snapshot_within_its_load(case):
    grid, island, _ = case
    loads = bus_load_mw(grid)
    bus, load = max(loads.items(), key=lambda item: item[1])
    assert actions_of(grid, island, sheds={bus: load}, trips=[])[0].amount_mw == load  # all of it is allowed
    refused_actions('shed_beyond_load', grid, island, sheds={bus: load + 0.01}, trips=[])
    refused_actions('shed_beyond_load', grid, island, sheds={bus: load / 2 + 0.01}, trips=[],
                    shed_before_mw={bus: load / 2})
    no_load = next(b for b in grid.buses if loads.get(b, 0.0) <= 0)
    refused_actions('unknown_load_bus', grid, island, sheds={no_load: 1.0}, trips=[])
    refused_actions('unknown_load_bus', grid, island, sheds={max(grid.buses) + 1: 1.0}, trips=[])
    for bad in (0.0, -5.0, float('nan'), float('inf')):
        refused_actions('bad_value', grid, island, sheds={bus: bad}, trips=[])
    refused_actions('unknown_generator', grid, island, sheds={}, trips=['GENROU_999'])
    name = grid.generators[0].name
    refused_actions('duplicate_action', grid, island, sheds={}, trips=[name, name])
    buses = sorted(island)
    with pytest.raises(Refusal) as info:
        plan_actions(grid, buses, [island[b] for b in buses], [bus, bus], [1.0, 1.0], [], max_actions=10)
    assert info.value.reason == 'duplicate_action'
    with pytest.raises(Refusal) as info:
        plan_actions(grid, buses, [island[b] for b in buses], [bus], [1.0, 2.0], [], max_actions=10)
    assert info.value.reason == 'array_length'
    refused_actions('too_many_actions', grid, island, sheds={bus: 1.0}, trips=[name], max_actions=1)


def test_no_island_is_left_with_load_and_no_running_machine(case):
    grid, island, _ = case
    loads = bus_load_mw(grid)
    for k in sorted(set(island.values())):
        machines = [g.name for g in grid.generators if island[g.bus] == k and g.p_max_mw > 0]
        load = sum(mw for b, mw in loads.items() if island[b] == k)
        if load <= 1e-6:
            continue
        refused_actions('island_without_generation', grid, island, sheds={}, trips=machines)
        # The last machine tripped by an earlier decision counts as well.
        if len(machines) > 1:
            refused_actions('island_without_generation', grid, island, sheds={}, trips=machines[1:],
                            tripped_before={machines[0]: 'd0'})
        # With all of the island's load shed, tripping its machines de-energises nothing that is served.
        everything = {b: mw for b, mw in loads.items() if island[b] == k and mw > 0}
        if sum(everything.values()) >= load - 1e-6:
            actions_of(grid, island, sheds=everything, trips=machines)
