"""`controlled-islanding partition`: split a grid into islands for given coherent generator groups."""

from __future__ import annotations

import argparse
import json

from controlled_islanding.commands import CliError

HELP = 'split a grid into islands for given coherent generator groups (constrained spectral clustering)'

DESCRIPTION = """\
Split a grid into islands, one per coherent generator group, by the paper's constrained spectral
clustering (eqs. 4-8), and print the islands, the lines to open and each island's power balance.

A group is a set of generators that swing together, given by their terminal BUS numbers, comma
separated: --group 30,37,38. Give one --group per group; together they must name every generator bus
exactly once. One group means "no split". An outage is a branch taken out of service before splitting,
given by its id or by its two end buses in either order: --outage 16-17 (repeat for several).

Flows (the edge weights of eq. 4): by default the AC power flow of the intact case with the outaged
branches then removed ("pre": the paper splits on pre-fault flows); --flows post runs the AC power flow
with the outages applied. Generation per island is scheduled dispatch; load to shed = max(0, load -
generation). Disrupted power is eq. 9: the sum over cut lines of (|P_from| + |P_to|) / 2, MW.

Example (the paper's case 1, Table I):
  controlled-islanding partition --case ieee39 --outage 16-17 --outage 1-2 \\
      --group 30,37,38 --group 31,32,33,34,35,36,39 --json
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the partition options."""
    parser.add_argument('--case', default='ieee39',
                        help='MATPOWER case: a name PYPOWER ships (ieee39 = case39, case14, ...) or a .m/.py file '
                             '(default: ieee39)')
    parser.add_argument('--outage', action='append', default=[], metavar='FROM-TO',
                        help='branch out of service: id or bus pair, e.g. 16-17 (repeatable)')
    parser.add_argument('--group', action='append', default=[], metavar='BUS,BUS,...',
                        help='generator buses of one coherent group, e.g. 30,37,38 (repeat per group)')
    parser.add_argument('--flows', choices=('pre', 'post'), default='pre',
                        help='flows for the weights: pre-outage flows with outaged branches removed (default), '
                             'or the post-outage AC power flow')
    parser.add_argument('--beta', type=float, default=0.2,
                        help='eq. 7 threshold as a fraction of its feasibility bound (default 0.2)')
    parser.add_argument('--no-refine', action='store_true',
                        help="stop at the paper's method (eqs. 4-8, k-medoids, repair): no single-bus moves that "
                             'lower the disrupted flow afterwards')
    parser.add_argument('--json', action='store_true', help='print one JSON object instead of a table')


def _parse_groups(texts: list[str], grid) -> dict[str, int]:
    """Map generator names to groups from --group bus lists, naming any bad value."""
    if not texts:
        raise CliError('give at least one --group BUS,BUS,... (generator buses of a coherent group)')
    at_bus = grid.generator_by_bus()
    buses = set(grid.buses)
    seen: dict[int, int] = {}
    groups: dict[str, int] = {}
    for k, text in enumerate(texts):
        items = [s.strip() for s in text.split(',') if s.strip()]
        if not items:
            raise CliError(f'--group {text!r} is empty; give generator bus numbers separated by commas')
        for item in items:
            try:
                bus = int(item)
            except ValueError:
                raise CliError(f'--group {text!r}: {item!r} is not a bus number') from None
            if bus not in buses:
                raise CliError(f'--group {text!r}: bus {bus} is not a bus of {grid.name}')
            if bus not in at_bus:
                raise CliError(f'--group {text!r}: bus {bus} has no generator '
                               f'(generator buses: {",".join(map(str, sorted(at_bus)))})')
            if bus in seen:
                raise CliError(f'generator bus {bus} is named by two --group options; '
                               'each generator belongs to one group')
            seen[bus] = k
            for gen in at_bus[bus]:
                groups[gen.name] = k
    missing = sorted(set(at_bus) - set(seen))
    if missing:
        raise CliError(f'generator bus(es) {",".join(map(str, missing))} are in no --group; '
                       'the groups must cover every generator')
    return groups


def run(args: argparse.Namespace) -> int:
    """Partition the grid and print the result."""
    from controlled_islanding.core.grid import Grid, GridError
    from controlled_islanding.core.islanding import IslandingError, decide
    from controlled_islanding.core.spectral import ConstrainedSpectralPartition, SpectralError

    try:
        base = Grid.from_matpower(args.case)
        outages = [base.branches[i].branch_id for text in args.outage for i in base.find_branches(text)]
        groups = _parse_groups(args.group, base)
        if args.flows == 'pre':
            grid = base.with_flows().with_outages(outages)
        else:
            grid = base.with_outages(outages).with_flows()
        decision = decide(grid, groups, ConstrainedSpectralPartition(beta=args.beta, refine=not args.no_refine))
    except (GridError, IslandingError, SpectralError) as exc:
        raise CliError(str(exc)) from exc
    islands = [decision.island_buses(i) for i in range(decision.n_islands)]
    result = {
        'case': grid.name,
        'outages': outages,
        'flows': args.flows,
        'split': decision.split,
        'islands': islands,
        'cut_lines': [[b.from_bus, b.to_bus] for b in decision.cut_branches],
        'cut_branch_ids': list(decision.cut_branch_ids),
        'lines_cut': len(decision.cut_branches),
        'disrupted_mw': round(decision.disrupted_mw, 3),
        'island_balance': [
            {'island': i, 'generation_mw': round(g, 3), 'load_mw': round(ld, 3),
             'imbalance_mw': round(im, 3), 'shed_mw': round(sh, 3)}
            for i, (g, ld, im, sh) in enumerate(zip(decision.island_generation_mw, decision.island_load_mw,
                                                    decision.island_imbalance_mw, decision.island_shed_mw,
                                                    strict=True))],
    }
    if args.json:
        print(json.dumps(result))
        return 0
    print(f'{grid.name}: {len(islands)} island(s), flows {args.flows}, outages: {", ".join(outages) or "none"}')
    for i, buses in enumerate(islands):
        print(f'  island {i}: buses {",".join(map(str, buses))}')
    cut = ', '.join(f'{a}-{b}' for a, b in result['cut_lines']) or 'none'
    print(f'  open lines ({result["lines_cut"]}): {cut}')
    print(f'  disrupted power (eq. 9): {decision.disrupted_mw:.2f} MW')
    print(f'  {"island":>6} {"generation MW":>14} {"load MW":>10} {"imbalance MW":>13} {"shed MW":>9}')
    for row in result['island_balance']:
        print(f'  {row["island"]:>6} {row["generation_mw"]:>14.1f} {row["load_mw"]:>10.1f} '
              f'{row["imbalance_mw"]:>13.1f} {row["shed_mw"]:>9.1f}')
    return 0
