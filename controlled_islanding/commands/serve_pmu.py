"""`controlled-islanding serve-pmu BAG`: play a bag's PMU frames out as a C37.118.2 PMU/PDC over TCP."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from controlled_islanding.commands import CliError
from controlled_islanding.graph.processes import sigterm_as_interrupt

HELP = "play a bag's PMU frames as a C37.118.2 PMU/PDC TCP server (a lab PDC, or pdc_client, connects to it)"
DESCRIPTION = """\
Serves the PMU frames of a scenario bag as one IEEE C37.118.2 data stream over TCP: one PMU block per
station of the bag, each with the phasors VPOS (terminal voltage, V line to neutral) and IPOS (generator
current out of the machine, A), FREQ and DFREQ. A client (a PDC) sends COMMAND frames: CFG-2 for the
configuration, START to start its own playback from the bag's first frame, STOP to pause it.

Each DATA frame carries the bag frame's time tag as SOC/FRACSEC (the bags' simulated UTC, 2026-01-01) and
goes out at the bag's timing divided by --rate, counted from the client's START. Stations absent from a bag
frame are sent with STAT 0x8000 and NaN values; frames lost in the bag are not sent.

The bags hold per unit; volts and amperes use --base-kv for every bus and the snapshot's MVA base. Write the
channel map that says which channel is which generator bus (pdc_client's channel_map_file) with --write-map.

  controlled-islanding serve-pmu bags/ieee39_case2_g3_unstable --write-map build/ieee39.map.yaml
  controlled-islanding serve-pmu BAG --port 0 --format int   # any free port; 16-bit phasors scaled by PHUNIT
  ros2 run controlled_islanding pdc_client --ros-args -p servers:="['127.0.0.1:4712']" \\
      -p channel_map_file:=build/ieee39.map.yaml

It listens on 127.0.0.1 unless --host says otherwise (a PDC on another machine needs --host 0.0.0.0).
The first line printed names the address and port ("listening on HOST:PORT"). Ctrl-C stops it.
"""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the serve-pmu arguments."""
    parser.add_argument('bag', type=Path, help='rosbag2 bag with /pmu/frames and /network/snapshot')
    parser.add_argument('--host', default='127.0.0.1', help='address to listen on (default: 127.0.0.1)')
    parser.add_argument('--port', type=int, default=4712,
                        help='TCP port (default: 4712, the C37.118 convention; 0 = any free port)')
    parser.add_argument('--rate', type=float, default=1.0,
                        help='playback speed against the bag timing (default: 1.0, real time)')
    parser.add_argument('--idcode', type=int, default=1, help='IDCODE of the data stream (default: 1)')
    parser.add_argument('--format', choices=('float', 'int'), default='float',
                        help='phasors and FREQ as 32-bit floats, or 16-bit integers scaled by PHUNIT (default: float)')
    parser.add_argument('--base-kv', type=float, default=345.0,
                        help='base voltage of every PMU bus, kV line to line, to turn per unit into volts and '
                             'amperes (default: 345, every bus of IEEE 39 in MATPOWER case39)')
    parser.add_argument('--time-base', type=int, default=1_000_000,
                        help='TIME_BASE: FRACSEC fractions per second (default: 1000000, microseconds)')
    parser.add_argument('--stations', default='',
                        help='comma-separated stations to serve (default: all), to split the PMUs among servers')
    parser.add_argument('--write-map', type=Path, default=None, metavar='FILE',
                        help="write pdc_client's channel map for this stream to FILE")
    parser.add_argument('--once', action='store_true', help='exit after one client has received the whole bag')


def run(args: argparse.Namespace) -> int:
    """Serve the bag until Ctrl-C (or, with --once, until one stream is complete)."""
    from controlled_islanding.pmu.stream import PmuServer, PmuStreamError, load_bag_stream

    if not args.bag.exists():
        raise CliError(f'bag {args.bag} does not exist')
    if not 0 <= args.port <= 65535:
        raise CliError(f'--port {args.port} is not a TCP port')
    if not 0 <= args.idcode <= 0xFFFF:
        raise CliError(f'--idcode {args.idcode} does not fit in 16 bits')
    if args.base_kv <= 0 or args.rate <= 0:
        raise CliError('--base-kv and --rate must be positive')
    stations = tuple(s for s in args.stations.split(',') if s)
    try:
        stream = load_bag_stream(args.bag, idcode=args.idcode, base_kv=args.base_kv, integer=args.format == 'int',
                                 time_base=args.time_base, stations=stations)
    except PmuStreamError as exc:
        raise CliError(str(exc)) from exc
    if args.write_map is not None:
        args.write_map.parent.mkdir(parents=True, exist_ok=True)
        args.write_map.write_text(stream.channel_map.to_yaml())

    def say(line: str) -> None:
        print(f'serve-pmu: {line}', flush=True)

    # SIGTERM (a supervisor stopping us) ends the loop like Ctrl-C, so every socket is closed.
    try:
        with sigterm_as_interrupt(), PmuServer(stream, args.host, args.port, args.rate, log=say) as server:
            cfg = stream.config
            say(f'listening on {server.host}:{server.port} (IDCODE {cfg.idcode}, {len(cfg.pmus)} PMUs, '
                f'{len(stream.frames)} frames at {cfg.data_rate} frames/s, {args.format}, rate {args.rate})'
                + (f'; channel map {args.write_map}' if args.write_map else ''))
            server.serve(until=(lambda: server.streams_completed > 0) if args.once else (lambda: False))
    except PmuStreamError as exc:
        raise CliError(str(exc)) from exc
    except KeyboardInterrupt:
        say('stopped')
    return 0


if __name__ == '__main__':
    from controlled_islanding.commands import main

    sys.exit(main(['serve-pmu', *sys.argv[1:]]))
