"""`controlled-islanding export`: write an islanding decision in a form MATPOWER, pandapower or ANDES applies."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from controlled_islanding import atomic
from controlled_islanding.commands import CliError

HELP = 'write a decision as a MATPOWER case or a pandapower net with the cut applied, or as ANDES Toggle events'
DESCRIPTION = """\
Take an islanding decision and write what another tool needs to apply it, starting from the case the decision
was made on, set up as the simulator set it up (the scenario's loads and dispatch; branch ids match in either
orientation). The decision is read from any file the project writes it in:

  a replay or demo summary.json      the scenario of its bag in bags/index.yaml
  a testbed result                   a scenario's result.json, or the testbed's --json output or testbed.json
                                     (a list: --scenario NAME picks one); the scenario its path names
  a bag with IslandingDecision       a replay's results/.../output_bag: its last decision on a bag request,
                                     the scenario of the bag the summary.json beside it names
Anything else is refused ("not a decision: ..."), as is a case whose islands do not hold the load (after the
shed) and generation the decision counted on.

  --to matpower   NAME.m: the case with the cut branches (and the outages the decision saw) at status 0,
                  one reference bus per island and the load shed at the buses the decision's remedial
                  actions name (older decisions: each island's load cut by its load to shed), so that
                  each island's power flow solves on its own (MATPOWER, PYPOWER; for pandapower, --to pandapower);
                  the machines the decision trips stay in service: generation is the decision's scheduled one
  --to pandapower a pandapower net as JSON (pandapower.from_json): that case through pandapower's converter,
                  lines, transformers and impedances named by branch id, the cut ones in_service False,
                  one ext_grid per island, so pandapower.runpp solves every island
  --to andes      a JSON list of Toggle rows, one per cut branch at --at-s: for each row,
                  system.add('Toggle', row) before setup opens the line in a time-domain run

The outages are the scenario's trips before the decision's request. When the decision's scenario is not known,
give --case: a scenario YAML, or a case file or a case bundled with ANDES taken as it is (with any --outage).

Examples:
  controlled-islanding export results/demo-<UTC>/summary.json --to matpower -o islanded.m
  controlled-islanding export results/replay-<bag>-<UTC>/output_bag --to pandapower -o islanded.json
  controlled-islanding export results/testbed-<UTC>/ieee14_g1_unstable/result.json --to pandapower -o cut.json
  controlled-islanding testbed --all-unstable --json > runs.json
  controlled-islanding export runs.json --scenario ieee39_g6g7_unstable --to matpower -o g6g7.m
  controlled-islanding export summary.json --to andes --at-s 7.05 -o toggles.json
  controlled-islanding export summary.json --to matpower --case bags/ieee14_g1_unstable.yaml -o cut.m
  controlled-islanding export summary.json --to matpower --case ieee14/ieee14_full.xlsx --outage 2-4 -o cut.m
"""

def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the export options."""
    parser.add_argument('decision', type=Path,
                        help='a summary.json of replay or demo, a testbed result or list of them, or an output bag')
    parser.add_argument('--scenario', default=None, help='the testbed result to take, by scenario name, of a list')
    parser.add_argument('--to', required=True, choices=('matpower', 'pandapower', 'andes'), help='the target tool')
    parser.add_argument('-o', '--output', type=Path, required=True, help='file to write (NAME.m, or a .json)')
    parser.add_argument('--case', default=None,
                        help='scenario YAML, or a case file or one bundled with ANDES such as ieee39/ieee39_full.xlsx')
    parser.add_argument('--addfile', default=None, help='PSS/E .dyr file for a .raw case')
    parser.add_argument('--outage', action='append', default=None,
                        help='branch already out when the decision was made (repeatable)')
    parser.add_argument('--at-s', type=float, default=None,
                        help='ANDES: simulation time, s from the start of the run, the Toggles open the lines at')


def run(args: argparse.Namespace) -> int:
    """Export the decision."""
    from controlled_islanding.evaluation import export
    from controlled_islanding.evaluation.decision_file import decision_and_case, read_decision

    if args.to == 'andes' and args.at_s is None:
        raise CliError('--to andes needs --at-s: the simulation time (s from the start of the run) to open the lines')
    try:
        source = read_decision(args.decision, args.scenario)
        decision, ss, case = decision_and_case(source, args.case, args.addfile, args.outage)
        if args.to == 'matpower':
            ppc = export.matpower_case(ss, decision)
            export.write_matpower(ppc, args.output)
        elif args.to == 'pandapower':
            export.pandapower_json(export.pandapower_net(ss, decision), args.output)
        else:
            rows = export.andes_toggles(ss, decision, args.at_s)
            atomic.write_text(args.output, json.dumps(rows, indent=2) + '\n')
    except export.ExportError as exc:
        raise CliError(str(exc)) from exc
    print(f'{args.output}: {source.what}: {len(decision.cut_branch_ids)} cut branch(es) '
          f'{", ".join(decision.cut_branch_ids)}, {len(decision.islands)} islands, case {case}')
    return 0
