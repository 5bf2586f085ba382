"""`controlled-islanding simulate`: ANDES time-domain simulation of a scenario into a PMU bag."""

from __future__ import annotations

import argparse
import time
from pathlib import Path

from controlled_islanding.commands import CliError, progress_bar
from controlled_islanding.locations import bags_dir

HELP = 'simulate a scenario YAML in ANDES and record PMU frames and ground truth in a bag'

DESCRIPTION = """\
Run a cascading-outage scenario in ANDES (time-domain simulation) and write a rosbag2 bag (MCAP) with
the PMU frames, the pre-fault network snapshot, the branch trips, the islanding request, and the ground
truth (/truth/rotor_angles, /truth/coherent_groups) that no node may read.

Example scenario (bags/ieee39_g6g7_unstable.yaml):

  case: ieee39/ieee39_full.xlsx        # ANDES case: path relative to the YAML, or bundled with ANDES
  # dispatch: case39                   # optional MATPOWER loads and generator P, matched by bus
  # load_scale: 1.1                    # optional: scales loads and PV dispatch
  step_s: 0.008333333333333333         # integration step, s
  end_s: 9.0                           # simulated time, s
  events:
    - {type: fault, bus: 22, start_s: 5.0, clear_s: 5.25}           # 3-phase bus fault
    - {type: trip, branch: 21-22, t_s: 5.25}                        # branch opens
    # - {type: fault, branch: 16-17, position: 0.5, start_s: 7.0, clear_s: 7.1}   mid-line fault
  pmu: {rate_fps: 60, buses: generators, noise_tve: 0.005}          # 60 or 30 fps; TVE <= 0.01
  seed: 1
  impairments: {frame_loss_rate: 0.05, initial_gap_s: 6.0, delay_mean_s: 0.05, delay_jitter_s: 0.02,
                silent_pmu_bus: 35, silent_from_s: 6.0}             # each optional
  islanding_request_s: 7.0

The full schema is in controlled_islanding/sim/scenario.py. Same YAML and seed give the same messages.

  controlled-islanding simulate bags/ieee39_g6g7_unstable.yaml --out /tmp/g6g7 --force
  controlled-islanding simulate --all --force                # regenerate every scenario in bags/ (index.yaml excepted)
  controlled-islanding simulate --update-manifest            # rewrite bags/index.yaml from the bags
"""

DEFAULT_BAGS_DIR = bags_dir()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the simulate options."""
    parser.add_argument('scenarios', nargs='*', type=Path, metavar='SCENARIO.yaml',
                        help='scenario files; those differing only in PMUs, seed or impairments share one '
                             'ANDES run')
    parser.add_argument('--out', type=Path, metavar='BAG',
                        help='bag directory to write (one scenario only; default: the scenario name next to its '
                             'YAML file)')
    parser.add_argument('--all', nargs='?', const=DEFAULT_BAGS_DIR, type=Path, metavar='DIR', dest='all_dir',
                        help='simulate every scenario YAML in DIR (default bags/), each into DIR/<name>')
    parser.add_argument('--force', action='store_true', help='replace existing bags')
    parser.add_argument('--update-manifest', nargs='?', const=DEFAULT_BAGS_DIR / 'index.yaml', type=Path,
                        metavar='INDEX', help='after simulating, rewrite the manifest (default bags/index.yaml) '
                                              'from every bag listed with a YAML beside it')
    parser.add_argument('--check', action='store_true',
                        help='simulate into a scratch directory and compare with the committed bags instead of '
                             'writing them: exit 1 if any message differs (the suite regenerates a sample; '
                             '--all bags --check checks every bag, about 13 minutes)')


def run(args: argparse.Namespace) -> int:
    """Simulate every scenario given, then optionally rebuild the manifest."""
    from controlled_islanding.sim.andes_sim import SimulationError
    from controlled_islanding.sim.bag import BagWriteError, run_scenario
    from controlled_islanding.sim.manifest import scenario_files
    from controlled_islanding.sim.scenario import ScenarioError, load_scenario

    if args.all_dir is not None:
        if not args.all_dir.is_dir():
            raise CliError(f'--all: {args.all_dir} is not a directory')
        args.scenarios = [*args.scenarios, *scenario_files(args.all_dir)]
    if not args.scenarios and args.update_manifest is None:
        raise CliError('give at least one SCENARIO.yaml, --all, or --update-manifest')
    if args.out is not None and len(args.scenarios) != 1:
        raise CliError(f'--out names one bag but {len(args.scenarios)} scenarios were given')
    try:
        scenarios = [load_scenario(p) for p in args.scenarios]
    except ScenarioError as exc:
        raise CliError(str(exc)) from None
    # Scenarios sharing one ANDES run are simulated once when they follow each other.
    scenarios.sort(key=lambda s: (repr(s.simulation_key()), s.name))
    if args.check:
        return _check(scenarios)
    bar = progress_bar(len(scenarios), 'simulate', 'scenario')
    for sc in scenarios:
        bar.update()
        out = args.out if args.out is not None else sc.path.parent / sc.name
        start = time.monotonic()
        try:
            result = run_scenario(sc, out, force=args.force)
        except (ScenarioError, SimulationError, BagWriteError) as exc:
            raise CliError(str(exc)) from None
        k = max(result.groups.values()) + 1
        print(f'{result.bag}: {result.n_frames} PMU frames, {k} true group(s), {time.monotonic() - start:.1f} s',
              flush=True)
    if args.update_manifest is not None:
        from controlled_islanding.sim.manifest import ManifestError, write_manifest

        try:
            path = write_manifest(args.update_manifest, progress=True)
        except ManifestError as exc:
            raise CliError(str(exc)) from None
        print(f'{path}: updated')
    return 0


def _check(scenarios: list) -> int:
    """Regenerate each scenario into a scratch directory and compare it with its committed bag."""
    import tempfile

    from controlled_islanding.sim.andes_sim import SimulationError
    from controlled_islanding.sim.bag import message_difference, run_scenario
    from controlled_islanding.sim.scenario import ScenarioError

    differing = 0
    with tempfile.TemporaryDirectory(prefix='simulate-check-') as scratch:
        for sc in scenarios:
            committed = sc.path.parent / sc.name
            start = time.monotonic()
            if not committed.is_dir():
                verdict = 'no committed bag'
            else:
                try:
                    fresh = run_scenario(sc, Path(scratch) / sc.name).bag
                except (ScenarioError, SimulationError) as exc:
                    raise CliError(str(exc)) from None
                verdict = message_difference(fresh, committed) or 'same messages'
            differing += verdict != 'same messages'
            print(f'{sc.name}: {verdict} ({time.monotonic() - start:.1f} s)', flush=True)
    return 1 if differing else 0
