"""`controlled-islanding export`: write an islanding decision in a form MATPOWER, pandapower or ANDES applies."""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from controlled_islanding import atomic
from controlled_islanding.commands import CliError

HELP = 'write a decision as a MATPOWER case or a pandapower net with the cut applied, or as ANDES Toggle events'
DESCRIPTION = """\
Take the decision of a replay or demo (its summary.json) and write what another tool needs to apply it,
starting from the ANDES case the network came from (branch ids match in either orientation):

  --to matpower   NAME.m: the case with the cut branches (and the outages the decision saw) at status 0,
                  one reference bus per island and each island's load cut by its load to shed, so that
                  each island's power flow solves on its own (MATPOWER, PYPOWER; for pandapower, --to pandapower)
  --to pandapower a pandapower net as JSON (pandapower.from_json): that case through pandapower's converter,
                  lines, transformers and impedances named by branch id, the cut ones in_service False,
                  one ext_grid per island, so pandapower.runpp solves every island
  --to andes      a JSON list of Toggle rows, one per cut branch at --at-s: for each row,
                  system.add('Toggle', row) before setup opens the line in a time-domain run

The case and the outages are read from the bag's scenario in bags/index.yaml when the summary names a
manifest bag; otherwise give --case (a file, or a case bundled with ANDES) and any --outage.

Examples:
  controlled-islanding export results/demo-<UTC>/summary.json --to matpower -o islanded.m
  controlled-islanding export summary.json --to pandapower -o islanded.json
  controlled-islanding export summary.json --to andes --at-s 7.05 -o toggles.json
  controlled-islanding export summary.json --to matpower --case ieee14/ieee14_full.xlsx --outage 2-4 -o cut.m
"""

def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the export options."""
    parser.add_argument('decision', type=Path, help='summary.json written by replay or demo')
    parser.add_argument('--to', required=True, choices=('matpower', 'pandapower', 'andes'), help='the target tool')
    parser.add_argument('-o', '--output', type=Path, required=True, help='file to write (NAME.m, or a .json)')
    parser.add_argument('--case', default=None,
                        help='case file, or a case bundled with ANDES such as ieee39/ieee39_full.xlsx')
    parser.add_argument('--addfile', default=None, help='PSS/E .dyr file for a .raw case')
    parser.add_argument('--outage', action='append', default=None,
                        help='branch already out when the decision was made (repeatable)')
    parser.add_argument('--at-s', type=float, default=None,
                        help='ANDES: simulation time, s from the start of the run, the Toggles open the lines at')


def _manifest_case(bag: str) -> tuple[str | None, str | None, list[str]]:
    """Return the case, addfile and outages of the manifest entry whose bag the summary names, if any."""
    import yaml

    from controlled_islanding.locations import bags_dir
    from controlled_islanding.sim.manifest import manifest_entries
    from controlled_islanding.sim.scenario import resolve_case

    if not bag:
        return None, None, []
    for entry in manifest_entries():
        if Path(bag).name == entry.get('bag'):
            scenario_path = bags_dir() / entry['scenario']
            scenario = yaml.safe_load(scenario_path.read_text())
            case = str(resolve_case(scenario['case'], scenario_path.parent))
            addfile = (str(resolve_case(scenario['addfile'], scenario_path.parent, 'addfile'))
                       if scenario.get('addfile') else None)
            return case, addfile, list(entry.get('tripped_before_request', []))
    return None, None, []


def run(args: argparse.Namespace) -> int:
    """Export the decision."""
    from controlled_islanding.evaluation import export

    try:
        summary = json.loads(args.decision.read_text())
    except (OSError, ValueError) as exc:
        raise CliError(f'decision {args.decision}: cannot read it as JSON: {exc}') from exc
    if args.to == 'andes' and args.at_s is None:
        raise CliError('--to andes needs --at-s: the simulation time (s from the start of the run) to open the lines')
    case, addfile, outages = _manifest_case(str(summary.get('bag', '')))
    case, addfile = args.case or case, args.addfile or addfile
    outages = args.outage if args.outage is not None else outages
    if case is None:
        raise CliError(f'decision {args.decision}: its bag {summary.get("bag")!r} is not in bags/index.yaml; '
                       'give --case')
    try:
        decision = export.Decision.from_summary(summary, outages)
        ss = export.load_case(case, addfile)
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
    print(f'{args.output}: {len(decision.cut_branch_ids)} cut branch(es) {", ".join(decision.cut_branch_ids)}, '
          f'{len(decision.islands)} islands, case {case}')
    return 0
