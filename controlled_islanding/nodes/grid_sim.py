"""grid_sim: an ANDES time-domain simulation of a scenario as the grid the pipeline listens to and acts on.

It publishes what the field would: the pre-fault network snapshot, PMU frames at the scenario's rate (with its
noise and impairments, sim/pmu.PmuStream), branch status changes (the scenario's trips, and every branch
it opens on command), the scenario's islanding request, and /clock. It executes /breaker/commands, and nothing
else: the OPEN commands of one decision open their branches together, in one simulation step,
`breaker_operating_s` after the last of the decision's commands came (one switching event,
sim/closed_loop.SwitchingEvents; those that came within `command_wait_s` wall of the first, if some never come),
and `shed_delay_s` later its SHED_LOAD commands shed their amount at their bus and its TRIP_GENERATOR commands
trip their machine (sim/closed_loop.py says how). It decides no shed or trip of its own; the grid's own
protection (PRC-024 trips, UFLS) stays in the simulation. A command it cannot apply (an unset or CLOSE action, a
branch, bus or machine the case lacks, a shed beyond the bus's load) is listed as ignored. After `run_after_s` past
the request it publishes a post-islanding assessment per island on /grid/assessment
(diagnostic_msgs/DiagnosticArray, one status per island), writes it to `report_file` (JSON) and the
trajectories to `<report_file>.npz`, and exits.

Time. Stamps are sim time plus sim/bag.START_TIME_UNIX_S, as in the bags, and /clock carries it.
- `rate: 0` (default), lockstep: the simulation runs as fast as it can, but before it publishes the request it
  waits until /rotor_angles has caught up with the newest frame (at most `angles_wait_s` wall), and then it does
  not step past the request until the decision for it has come (at most `decision_timeout_s` wall; after each
  third of it without one, the request is sent again with its id, as bag_player does) and, for a split, its
  breaker commands (at most `command_wait_s` wall after the decision; fewer than the cut's branches is
  reported). Frames tagged at or before the request but delivered after it (delay impairments) are sent while it
  waits, and /clock is published again every 50 ms (wall), for a node restarted meanwhile. Sim time is frozen
  while the graph works, so the wall time from publishing the request to receiving the command is charged to
  sim time: the branch opens at request + that latency + breaker_operating_s.
- `trigger: out_of_step` (default `scenario`): the request is not the scenario's but published at the first step
  where the measured rotor angles (/rotor_angles, against the first ones received) show two machines more than
  90 deg apart while no delivered PMU voltage is below 0.5 pu (sim/closed_loop.out_of_step); the run is then
  extended to run_after_s past it. In lockstep each step waits (at most `trigger_wait_s` wall) until
  /rotor_angles has answered every frame sent, so the trigger time does not depend on how busy the machine is.
  An answer that does not split re-arms the trigger: it requests again (a new request id) at the next step
  with new angles on which the condition still holds, at most `trigger_max_requests` times in all. Why: 90 deg
  is visible separation, not yet loss of synchronism; stable swings pass it (Nordic 44, the bus-6000 fault
  cleared in 270 ms: 131 deg) and coherency's separation rule rightly keeps one group until the pair runs away
  (IEEE 39 G6-G7: the trigger at 5.39 s, two groups from 5.55 s, from 5.43 s with the runaway test of 63828a7),
  so a one-shot trigger asked once, too early, and never again. A relay is not disabled by a request that was
  answered; the operator-side bound is the cap.
- `trigger: monitor`: grid_sim raises no request; the stability monitor (nodes/stability_monitor.py) does, on the
  angles it reads. The first IslandingRequest heard on the topic is the run's request: in lockstep each step waits
  (at most `trigger_wait_s` wall) until /rotor_angles has answered every frame sent, then takes what came (the
  monitor judges each sample as it arrives), and once a request is heard the simulation is held for its decision
  and commands as for its own, the wall time charged from the request's stamp. With no request, the run is judged
  from the scenario's own request time, as no action is.
- `rate: R > 0`: paced at R times real time, nothing waits; a command opens its branch at max(its stamp, the sim
  time it arrived) + breaker_operating_s, the decision's latest. If ANDES is slower than R x real time, the
  pace is ANDES'.
"""

from __future__ import annotations

import json
import math
import sys
import time
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from builtin_interfaces.msg import Time
from controlled_islanding_msgs.msg import (
    BranchStatus,
    BreakerCommand,
    IslandingDecision,
    IslandingRequest,
    NetworkSnapshot,
    PmuFrame,
    PmuMeasurement,
    RotorAngles,
)
from diagnostic_msgs.msg import DiagnosticArray, DiagnosticStatus, KeyValue
from rclpy.executors import SingleThreadedExecutor
from rclpy.node import Node
from rosgraph_msgs.msg import Clock

from controlled_islanding import atomic
from controlled_islanding.core.grid import Grid
from controlled_islanding.ros.diagnostics import Diagnostics
from controlled_islanding.ros.endpoints import qos_for
from controlled_islanding.ros.params import NodeSetupError
from controlled_islanding.ros.spin import spin_node
from controlled_islanding.sim.bag import PDC_FRAME_ID, START_TIME_UNIX_S
from controlled_islanding.sim.closed_loop import (
    ClosedLoopError,
    GridRun,
    LoopConfig,
    Sample,
    SwitchingEvent,
    SwitchingEvents,
    out_of_step,
)
from controlled_islanding.sim.pmu import Frame, PmuStream
from controlled_islanding.sim.scenario import ScenarioError, load_scenario
from controlled_islanding.wire import topics
from controlled_islanding.wire.messages import bus_voltage_angles, dynamic_data_fields, nominal_frequency_hz

ASSESSMENT_TOPIC = '/grid/assessment'
_CLOCK_HEARTBEAT_S = 0.05
_REQUEST_ATTEMPTS = 3
_START_NS = START_TIME_UNIX_S * 1_000_000_000


def _stamp(t_s: float) -> Time:
    ns = _START_NS + int(round(t_s * 1e9))
    return Time(sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _sim_s(stamp: Any) -> float:
    return (stamp.sec * 1_000_000_000 + stamp.nanosec - _START_NS) * 1e-9


def snapshot_msg(grid: Grid) -> NetworkSnapshot:
    """Return the NetworkSnapshot of a grid, stamped at sim time 0 (as sim/bag.py writes it)."""
    msg = NetworkSnapshot(
        case_name=grid.name, base_mva=float(grid.base_mva), nominal_frequency_hz=nominal_frequency_hz(grid),
        bus_numbers=[int(b) for b in grid.buses], bus_voltage_angle_rad=bus_voltage_angles(grid),
        branch_ids=[b.branch_id for b in grid.branches], branch_breaker_ids=[b.breaker for b in grid.branches],
        branch_from_bus=[b.from_bus for b in grid.branches], branch_to_bus=[b.to_bus for b in grid.branches],
        branch_in_service=[b.in_service for b in grid.branches],
        branch_p_from_mw=[float(x) for x in grid.p_from_mw], branch_p_to_mw=[float(x) for x in grid.p_to_mw],
        generator_names=[g.name for g in grid.generators], generator_bus=[g.bus for g in grid.generators],
        generator_p_mw=[float(g.p_mw) for g in grid.generators],
        generator_p_max_mw=[float(g.p_max_mw) for g in grid.generators],
        generator_xq_pu=[float(g.xq_pu) for g in grid.generators],
        generator_ra_pu=[float(g.ra_pu) for g in grid.generators],
        **{f: list(v) if f == 'generator_model' else v.tolist()
           for f, v in dynamic_data_fields(grid.generators).items()},
        load_bus=[ld.bus for ld in grid.loads], load_p_mw=[float(ld.p_mw) for ld in grid.loads],
        load_q_mvar=[float(ld.q_mvar) for ld in grid.loads])
    msg.header.stamp = _stamp(0.0)
    msg.header.frame_id = 'andes_power_flow'
    return msg


def frame_msg(frame: Frame) -> PmuFrame:
    """Return the PmuFrame of a frame."""
    msg = PmuFrame(measurements=[
        PmuMeasurement(station_id=frame.station_ids[j], bus=int(frame.buses[j]),
                       voltage_magnitude_pu=float(frame.v_mag_pu[j]), voltage_angle_rad=float(frame.v_angle_rad[j]),
                       current_magnitude_pu=float(frame.i_mag_pu[j]), current_angle_rad=float(frame.i_angle_rad[j]),
                       frequency_hz=float(frame.frequency_hz[j]), rocof_hz_per_s=float(frame.rocof_hz_per_s[j]),
                       stat=int(frame.stat[j]))
        for j in range(len(frame.buses))])
    msg.header.stamp = _stamp(frame.tag_s)
    msg.header.frame_id = PDC_FRAME_ID
    return msg


def _expected_items(decision: IslandingDecision) -> list[str]:
    """Return what a split decision's commands switch: its cut's branch ids, then its remedial actions' keys."""
    return ([str(b) for b in decision.cut_branch_ids] + [f'shed:{int(b)}' for b in decision.shed_bus]
            + [f'trip:{n}' for n in decision.trip_generator_names])


class GridSimNode(Node):
    """Runs the scenario's simulation in its main loop; see the module docstring."""

    def __init__(self) -> None:
        super().__init__('grid_sim')
        self.declare_parameter('scenario', '')
        self.declare_parameter('rate', 0.0)
        self.declare_parameter('breaker_operating_s', 0.05)
        self.declare_parameter('shed_delay_s', 0.2)
        self.declare_parameter('run_after_s', 3.0)
        self.declare_parameter('decision_timeout_s', 30.0)
        self.declare_parameter('command_wait_s', 2.0)
        self.declare_parameter('angles_wait_s', 5.0)
        self.declare_parameter('wait_for_subscribers_s', 20.0)
        self.declare_parameter('min_subscribers', [''])
        self.declare_parameter('report_file', '')
        self.declare_parameter('progress', False)
        self.declare_parameter('trigger', 'scenario')
        self.declare_parameter('trigger_wait_s', 0.5)
        self.declare_parameter('trigger_max_requests', 20)
        path = self.get_parameter('scenario').value
        if not path:
            raise NodeSetupError('parameter scenario is empty; it must name a scenario YAML (see bags/*.yaml)')
        self.rate = float(self.get_parameter('rate').value)
        if self.rate < 0:
            raise NodeSetupError(f'parameter rate={self.rate} must be 0 (lockstep) or positive (paced)')
        config = LoopConfig(breaker_operating_s=float(self.get_parameter('breaker_operating_s').value),
                            shed_delay_s=float(self.get_parameter('shed_delay_s').value),
                            run_after_s=float(self.get_parameter('run_after_s').value))
        if config.breaker_operating_s < 0 or config.shed_delay_s < 0 or config.run_after_s <= 0:
            raise NodeSetupError('breaker_operating_s and shed_delay_s must be >= 0, run_after_s > 0')
        try:
            self.scenario = load_scenario(path)
            self.grid_run = GridRun(self.scenario, config, progress=bool(self.get_parameter('progress').value))
        except (ScenarioError, ClosedLoopError, RuntimeError) as exc:
            raise NodeSetupError(f'scenario {path}: {exc}') from exc
        self.pmu = PmuStream(self.scenario, self.grid_run.generator_names, self.grid_run.generator_buses,
                             self.grid_run.bus_numbers, float(self.grid_run.ss.config.freq))
        self.report_file = self.get_parameter('report_file').value
        self.trigger = str(self.get_parameter('trigger').value)
        if self.trigger not in ('scenario', 'out_of_step', 'monitor'):
            raise NodeSetupError(f'parameter trigger={self.trigger!r} must be scenario, out_of_step or monitor')
        self.judged_from_s = self.scenario.request_s  # without any request, the run is judged from here
        self.heard: IslandingRequest | None = None  # trigger monitor: the first request heard on the topic
        if self.trigger != 'scenario':  # the request comes when the angles say so, not at the scenario's time
            self.scenario = replace(self.scenario, request_s=math.inf)
        self.angle_ref: dict[str, float] = {}
        self.answered_s = -math.inf  # sim time of the last request answered without a split (trigger re-arm)
        self.angle_now: dict[str, float] = {}
        self.frame_v_pu = np.zeros(0)
        pub = {t: self.create_publisher(cls, topics.relative(t), qos_for(t)) for t, cls in (
            (topics.NETWORK_SNAPSHOT, NetworkSnapshot), (topics.PMU_FRAMES, PmuFrame),
            (topics.BRANCH_STATUS, BranchStatus), (topics.ISLANDING_REQUEST, IslandingRequest))}
        self.pubs = pub
        self.clock_pub = self.create_publisher(Clock, topics.CLOCK, qos_for(topics.CLOCK))
        self.clock_s: float | None = None  # the last /clock published, sim s, and when (wall, monotonic s)
        self.clock_wall_s = 0.0
        self.assessment_pub = self.create_publisher(DiagnosticArray, topics.relative(ASSESSMENT_TOPIC),
                                                    qos_for(topics.DIAGNOSTICS))
        self.create_subscription(BreakerCommand, topics.relative(topics.BREAKER_COMMANDS), self._on_command,
                                 qos_for(topics.BREAKER_COMMANDS))
        self.create_subscription(IslandingDecision, topics.relative(topics.ISLANDING_DECISION), self._on_decision,
                                 qos_for(topics.ISLANDING_DECISION))
        self.create_subscription(RotorAngles, topics.relative(topics.ROTOR_ANGLES), self._on_angles,
                                 qos_for(topics.ROTOR_ANGLES))
        if self.trigger == 'monitor':
            self.create_subscription(IslandingRequest, topics.relative(topics.ISLANDING_REQUEST), self._on_request,
                                     qos_for(topics.ISLANDING_REQUEST))
        self.diag = Diagnostics(self)
        self.requests_made = 1
        self.request_id = f'{self.scenario.name}/closed-loop-request-1'
        self.decisions: dict[str, IslandingDecision] = {}
        self.commands: list[tuple[float, float, BreakerCommand]] = []  # (wall s, sim s at receipt, msg)
        self.handled_commands: set[str] = set()
        self.remedial: dict[str, dict[str, BreakerCommand]] = {}  # decision -> item -> its SHED or TRIP command
        self.switching = SwitchingEvents(float(self.get_parameter('command_wait_s').value))
        self.newest_angle_s = -1.0
        self.newest_frame_s = -1.0
        self.queue: list[Frame] = []  # frames computed, not yet delivered
        self.changes = list(self.grid_run.scheduled_changes)
        self.request_sent_wall: float | None = None
        self.request_sent = False
        self.held_wall_s = 0.0  # lockstep: wall time the simulation was held at the request
        self.events: list[dict[str, Any]] = []
        self.wall_start = 0.0
        self._exec: SingleThreadedExecutor | None = None
        self.t_now = 0.0
        mode = 'lockstep' if not self.rate else f'{self.rate}x real time'
        self.get_logger().info(f'{self.scenario.name}: {len(self.grid_run.bus_numbers)} buses, '
                               f'{len(self.grid_run.generator_names)} machines, request at '
                               f'{self.scenario.request_s} s, run to {self.grid_run.run_until_s} s, {mode}')

    # --- subscriptions -------------------------------------------------------------------------------------
    def _on_command(self, msg: BreakerCommand) -> None:
        self.diag.arrived()
        self.commands.append((time.monotonic(), self.t_now, msg))

    def _on_decision(self, msg: IslandingDecision) -> None:
        self.decisions.setdefault(msg.request_id, msg)

    def _on_request(self, msg: IslandingRequest) -> None:
        if self.heard is None:
            self.heard = msg

    def _on_angles(self, msg: RotorAngles) -> None:
        self.newest_angle_s = max(self.newest_angle_s, _sim_s(msg.header.stamp))
        for name, angle, ok in zip(msg.generator_names, msg.angle_rad, msg.valid, strict=True):
            if ok and math.isfinite(angle):
                self.angle_ref.setdefault(name, float(angle))
                self.angle_now[name] = float(angle)

    # --- helpers ---------------------------------------------------------------------------------------------
    def _spin(self, seconds: float = 0.0, done=lambda: False) -> bool:
        end = time.monotonic() + seconds
        while True:
            self._exec.spin_once(timeout_sec=0.0 if seconds <= 0 else min(0.02, max(0.0, end - time.monotonic())))
            if done() or time.monotonic() >= end:
                return done()
            # While it waits, /clock is said again: a node started meanwhile (restarted by the supervisor) has no
            # clock until it hears one, and rclpy reads /clock best effort (bag_player's clock_heartbeat_s).
            if self.clock_s is not None and time.monotonic() - self.clock_wall_s >= _CLOCK_HEARTBEAT_S:
                self._publish_clock(self.clock_s)

    def _publish_clock(self, t_s: float) -> None:
        self.clock_s, self.clock_wall_s = t_s, time.monotonic()
        self.clock_pub.publish(Clock(clock=_stamp(t_s)))

    def _status(self, t_s: float, branch_id: str, in_service: bool) -> None:
        f, t = self.grid_run.branch_ends[branch_id]
        msg = BranchStatus(branch_id=branch_id, from_bus=f, to_bus=t, in_service=in_service)
        msg.header.stamp = _stamp(t_s)
        msg.header.frame_id = 'andes'
        self.pubs[topics.BRANCH_STATUS].publish(msg)

    def _deliver(self, up_to_s: float, tags_up_to_s: float | None = None) -> None:
        """Publish queued frames delivered by up_to_s (or, while held, every frame tagged by tags_up_to_s)."""
        self.queue.sort(key=lambda f: f.delivery_s)
        keep = []
        for frame in self.queue:
            if frame.delivery_s <= up_to_s + 1e-9 or (tags_up_to_s is not None and frame.tag_s <= tags_up_to_s + 1e-9):
                self.pubs[topics.PMU_FRAMES].publish(frame_msg(frame))
                self.newest_frame_s = max(self.newest_frame_s, frame.tag_s)
                self.frame_v_pu = frame.v_mag_pu
            else:
                keep.append(frame)
        self.queue = keep

    def _item(self, run: GridRun, msg: BreakerCommand) -> str | None:
        """Return what a command switches (a branch id, 'shed:<bus>', 'trip:<machine>'), or None if it cannot apply."""
        if msg.action == BreakerCommand.ACTION_OPEN and msg.branch_id in run.branch_ends:
            return msg.branch_id
        if msg.action == BreakerCommand.ACTION_SHED_LOAD:
            load = run.island_load_mw([msg.bus])
            amount = float(msg.amount_mw)
            return f'shed:{msg.bus}' if math.isfinite(amount) and 0 < amount <= load * (1 + 1e-9) + 1e-9 else None
        if msg.action == BreakerCommand.ACTION_TRIP_GENERATOR and msg.generator_name in run.generator_names:
            return f'trip:{msg.generator_name}'
        return None

    def _execute(self, run: GridRun, wall: float, sim_at: float, msg: BreakerCommand) -> None:
        """Take a command: it joins its decision's switching event (sim/closed_loop.SwitchingEvents)."""
        if msg.command_id in self.handled_commands:
            return
        self.handled_commands.add(msg.command_id)
        item = self._item(run, msg)
        if item is None:
            self.events.append({'what': 'command ignored', 'command_id': msg.command_id, 'action': int(msg.action),
                                'branch_id': msg.branch_id, 'bus': int(msg.bus), 'generator': msg.generator_name,
                                'amount_mw': float(msg.amount_mw)})
            return
        if item != msg.branch_id:
            self.remedial.setdefault(msg.decision_id, {})[item] = msg
        cfg = run.config
        if self.rate == 0 and self.request_sent_wall is not None:
            # Lockstep: sim time stood still while the graph worked; charge the wall time it took.
            at = self.scenario.request_s + (wall - self.request_sent_wall) + cfg.breaker_operating_s
        else:
            at = max(_sim_s(msg.header.stamp), sim_at) + cfg.breaker_operating_s
        at = max(at, self.t_now)
        self.events.append({'what': 'command', 'command_id': msg.command_id, 'item': item,
                            'breaker_id': msg.breaker_id, 'decision_id': msg.decision_id,
                            'amount_mw': float(msg.amount_mw), 'command_stamp_s': _sim_s(msg.header.stamp),
                            'received_sim_s': sim_at, 'ready_at_s': at,
                            'wall_after_request_s': None if self.request_sent_wall is None
                            else wall - self.request_sent_wall})
        late = self.switching.add(msg.decision_id, item, at, wall)
        if late is not None:
            self._switch(run, late)

    def _switch(self, run: GridRun, event: SwitchingEvent) -> None:
        """Open one switching event's branches together; shed_delay_s later, apply its load sheds and trips."""
        at = max(event.at_s, self.t_now)
        actions = self.remedial.get(event.decision_id, {})
        branches = [i for i in event.items if i not in actions]
        if branches:
            run.open_branches(branches, at, why=f'open {", ".join(branches)}')
        shed = {int(actions[i].bus): float(actions[i].amount_mw) for i in event.items if i.startswith('shed:')}
        trips = [actions[i].generator_name for i in event.items if i.startswith('trip:')]
        after = at + run.config.shed_delay_s
        if shed:
            run.shed_loads(shed, after, why=f'shed {event.decision_id}')
        if trips:
            run.trip_generators(trips, after, why=f'reject {event.decision_id}')
        self.events.append({'what': 'switching event', 'decision_id': event.decision_id, 'branch_ids': branches,
                            'at_s': at, 'shed_mw_by_bus': shed, 'tripped': trips, 'actions_at_s': after,
                            'missing': list(event.missing), 'late': event.late})

    # --- the run ---------------------------------------------------------------------------------------------
    def _hook(self, run: GridRun, sample: Sample) -> None:
        t = sample.t_s
        self.t_now = t
        if self.rate > 0:
            lag = self.wall_start + t / self.rate - time.monotonic()
            if lag > 0:
                self._spin(lag)
        while self.changes and self.changes[0][0] <= t + 1e-9:
            t_c, bid, in_service = self.changes.pop(0)
            self._status(t_c, bid, in_service)
        frames = self.pmu.feed(sample)
        self.queue += frames
        if frames:
            self._publish_clock(min(t, frames[-1].tag_s) if not self.request_sent else t)
        if self.trigger != 'scenario' and not self.request_sent and self.rate == 0 and frames:
            # Lockstep: judge the angles of every frame sent so far. Without this wait the trigger saw whichever
            # angles the graph had answered while the simulation ran on, so it fired later the busier the machine
            # (IEEE 39 G6-G7: 5.625 s under load, 5.433 s with less).
            self._spin(float(self.get_parameter('trigger_wait_s').value),
                       lambda: self.newest_angle_s >= self.newest_frame_s - 1e-6)
        if (self.trigger == 'out_of_step' and not self.request_sent and self.newest_angle_s > self.answered_s
                and self._separated()):
            self.scenario = replace(self.scenario, request_s=t)
            run.scenario = self.scenario  # its outcome reports the request it answered
            run.run_until_s = max(run.run_until_s, t + run.config.run_after_s)
            run.ss.TDS.config.tf = run.run_until_s
            self.events.append({'what': 'out-of-step trigger', 'at_s': t,
                                'separation_rad': max(self.angle_now[n] - self.angle_ref[n] for n in self.angle_now)
                                - min(self.angle_now[n] - self.angle_ref[n] for n in self.angle_now)})
        if self.trigger == 'monitor' and not self.request_sent:
            self._spin()
            if self.heard is not None:
                self._heard(run, t)
        request_s = self.scenario.request_s
        if not self.request_sent and t >= request_s - 1e-9:
            self._deliver(request_s)
            self._request(run, t)
        self._deliver(t)
        self._spin()
        if self.rate > 0 and self.request_sent and self.request_id in self.decisions:  # lockstep re-arms in _request
            self._rearm(self.decisions[self.request_id])
        for wall, sim_at, msg in list(self.commands):
            self._execute(run, wall, sim_at, msg)
        self.commands.clear()
        expected = {d.decision_id: _expected_items(d) for d in self.decisions.values() if d.split}
        for event in self.switching.due(expected, time.monotonic()):
            self._switch(run, event)
        for action in run.actions:
            if action.what.startswith('open ') and action.applied_s is not None and not action.detail.get('said'):
                action.detail['said'] = True
                for bid in action.detail['branches']:
                    self._status(action.applied_s, bid, False)
                    self.events.append({'what': 'opened', 'branch_id': bid, 'at_s': action.applied_s})
        self.diag.arrived()

    def _separated(self) -> bool:
        names = list(self.angle_now)
        return out_of_step([self.angle_now[n] for n in names], [self.angle_ref[n] for n in names], self.frame_v_pu)

    def _heard(self, run: GridRun, t: float) -> None:
        """Take the monitor's request as the run's: its stamp is the request time; hold for its decision."""
        msg = self.heard
        request_s = min(_sim_s(msg.header.stamp), t)
        self.scenario = replace(self.scenario, request_s=request_s)
        run.scenario = self.scenario
        run.run_until_s = max(run.run_until_s, request_s + run.config.run_after_s)
        run.ss.TDS.config.tf = run.run_until_s
        self.request_id = msg.request_id
        self.request_sent_wall = time.monotonic()
        self.request_sent = True
        self.events.append({'what': 'request', 'request_id': msg.request_id, 'at_s': request_s, 'heard_at_s': t,
                            'from': 'stability monitor', 'reason': msg.reason})
        if self.rate == 0:
            self._hold(time.monotonic(), msg)

    def _request(self, run: GridRun, t: float) -> None:
        request_s = self.scenario.request_s
        self._publish_clock(request_s)
        if self.rate == 0 and self.newest_frame_s >= 0:
            t0 = time.monotonic()
            if not self._spin(float(self.get_parameter('angles_wait_s').value),
                              lambda: self.newest_angle_s >= self.newest_frame_s - 1e-6):
                self.get_logger().warning('lockstep: /rotor_angles did not catch up with the newest frame')
            self.held_wall_s += time.monotonic() - t0
        changes_before = sum(1 for t_c, _, _ in self.grid_run.scheduled_changes if 0.0 < t_c <= request_s)
        msg = IslandingRequest(request_id=self.request_id, branch_changes_before=changes_before,
                               reason=f'scenario {self.scenario.name}: islanding requested at {request_s:g} s '
                                      '(closed loop)')
        msg.header.stamp = _stamp(request_s)
        msg.header.frame_id = 'scenario'
        self.request_sent_wall = time.monotonic()
        self.pubs[topics.ISLANDING_REQUEST].publish(msg)
        self.request_sent = True
        self.events.append({'what': 'request', 'request_id': self.request_id, 'at_s': request_s})
        if self.rate > 0:
            return
        # Lockstep: hold the simulation at the request; frames already tagged go out while we wait.
        self._deliver(request_s, tags_up_to_s=request_s)
        self._hold(time.monotonic(), msg)

    def _hold(self, t0: float, msg: IslandingRequest) -> None:
        """Lockstep: wait for the request's decision and, for a split, its commands; then re-arm the trigger."""
        # In thirds, the request sent again with its id after each, as bag_player does: a partitioning node the
        # supervisor restarted lost the volatile request; one that has it answers each id once.
        for attempt in range(_REQUEST_ATTEMPTS):
            if attempt:
                self.get_logger().warning(f'lockstep: re-sending the islanding request ({attempt} of '
                                          f'{_REQUEST_ATTEMPTS - 1})')
                self.events.append({'what': 'request sent again', 'request_id': self.request_id,
                                    'after_wall_s': time.monotonic() - t0})
                self.pubs[topics.ISLANDING_REQUEST].publish(msg)
            got = self._spin(float(self.get_parameter('decision_timeout_s').value) / _REQUEST_ATTEMPTS,
                             lambda: self.request_id in self.decisions)
            if got:
                break
        decision = self.decisions.get(self.request_id)
        if not got or decision is None:
            self.get_logger().warning('lockstep: no decision for the request within decision_timeout_s')
            self.events.append({'what': 'no decision', 'waited_wall_s': time.monotonic() - t0})
        elif decision.split:
            want = len(_expected_items(decision))
            self._spin(float(self.get_parameter('command_wait_s').value),
                       lambda: sum(1 for _, _, c in self.commands if c.decision_id == decision.decision_id) >= want)
        self.held_wall_s += time.monotonic() - t0
        if got and decision is not None:
            self._rearm(decision)

    def _rearm(self, decision: IslandingDecision) -> None:
        """Re-arm the out-of-step trigger after an answer that does not split (see the module docstring)."""
        if (self.trigger != 'out_of_step' or decision.split
                or self.requests_made >= int(self.get_parameter('trigger_max_requests').value)):
            return
        request_s = self.scenario.request_s
        self.answered_s = request_s  # only angles newer than this request can fire it again
        self.requests_made += 1
        self.request_id = f'{self.scenario.name}/closed-loop-request-{self.requests_made}'
        self.scenario = replace(self.scenario, request_s=math.inf)
        self.request_sent = False
        self.events.append({'what': 'trigger re-armed', 'after_request_s': request_s, 'status': int(decision.status)})

    def simulate(self, executor: SingleThreadedExecutor) -> None:
        """Publish the snapshot, wait for subscribers, run the simulation in the loop, report, linger."""
        self._exec = executor
        self.pubs[topics.NETWORK_SNAPSHOT].publish(snapshot_msg(self.grid_run.grid))
        self._publish_clock(0.0)
        self._wait_for_subscribers()
        self.pubs[topics.NETWORK_SNAPSHOT].publish(snapshot_msg(self.grid_run.grid))
        self.wall_start = time.monotonic()
        self.grid_run.run(self._hook)
        self._deliver(float('inf'))
        self._report()
        self._spin(0.5)

    def _wait_for_subscribers(self) -> None:
        want: dict[str, int] = {}
        for item in self.get_parameter('min_subscribers').value:
            topic, _, count = item.rpartition('=')
            if topic:
                want[topic] = int(count)
        pubs = dict(self.pubs, **{topics.CLOCK: self.clock_pub})

        def ready() -> bool:
            return all(pubs[t].get_subscription_count() >= n for t, n in want.items() if t in pubs)

        if not self._spin(float(self.get_parameter('wait_for_subscribers_s').value), ready):
            lonely = [f'{t} ({pubs[t].get_subscription_count()} of {n})' for t, n in want.items()
                      if t in pubs and pubs[t].get_subscription_count() < n]
            self.get_logger().warning(f'starting although too few subscribers match {", ".join(lonely)}')

    def _report(self) -> None:
        run = self.grid_run
        decision = self.decisions.get(self.request_id)
        opened = [a for a in run.actions if a.what.startswith('open ') and a.applied_s is not None]
        opened_s = max((a.applied_s for a in opened), default=None)
        cut = [b for a in opened for b in a.detail['branches']]
        bus_island = None
        if decision is not None and decision.split and opened:
            bus_island = dict(zip((int(b) for b in decision.bus_numbers), (int(k) for k in decision.bus_island),
                                  strict=True))
        asked_s = run.scenario.request_s if math.isfinite(run.scenario.request_s) else self.judged_from_s
        outcome = run.outcome('closed loop', cut, bus_island, opened_s, opened_s if opened_s is not None else asked_s)
        array = DiagnosticArray()
        array.header.stamp = _stamp(self.t_now)
        for isl in outcome.islands:
            status = DiagnosticStatus(name=f'grid_sim: island {isl.island}', hardware_id=self.scenario.name,
                                      level=DiagnosticStatus.OK if isl.survived else DiagnosticStatus.WARN
                                      if isl.survived is None else DiagnosticStatus.ERROR,
                                      message='survived' if isl.survived else outcome.simulation_failed
                                      if isl.survived is None else '; '.join(isl.why_not))
            status.values = [KeyValue(key=k, value=str(v)) for k, v in (
                ('coherent', isl.coherent), ('max_pair_swing_rad', f'{isl.max_pair_swing_rad:.4f}'),
                ('f_nadir_hz', f'{isl.f_nadir_hz:.4f}'), ('f_peak_hz', f'{isl.f_peak_hz:.4f}'),
                ('v_min_pu', f'{isl.v_min_pu:.4f}'), ('v_max_pu', f'{isl.v_max_pu:.4f}'),
                ('shed_mw', f'{isl.shed_mw:.2f}'), ('load_mw', f'{isl.load_mw:.2f}'),
                ('machines_tripped', ','.join(isl.machines_tripped)), ('generators', ','.join(isl.generators)),
                ('rejected', ','.join(isl.rejected)), ('rejected_mw', f'{isl.rejected_mw:.2f}'))]
            array.status.append(status)
        self.assessment_pub.publish(array)
        verdict = ('every island survived' if outcome.all_survived else outcome.simulation_failed
                   if outcome.all_survived is None else 'NOT every island survived')
        self.get_logger().info(f'assessment: {verdict}; cut {cut or "none"} at {opened_s}; wall {run.wall_s:.1f} s')
        if self.report_file:
            report = {'scenario': str(self.scenario.path), 'outcome': outcome.summary(), 'events': self.events,
                      'request_id': self.request_id, 'held_wall_s': self.held_wall_s,
                      'config': run.config.__dict__, 'rate': self.rate}
            base = Path(self.report_file)
            with atomic.replacing(f'{base}.npz') as tmp, open(tmp, 'wb') as out:
                np.savez_compressed(out, t_s=outcome.t_s, delta_rad=outcome.delta_rad, bus_v_pu=outcome.bus_v_pu,
                                    generator_names=np.array(outcome.generator_names),
                                    generator_buses=np.array(outcome.generator_buses),
                                    bus_numbers=np.array(outcome.bus_numbers))
            atomic.write_text(base, json.dumps(report, indent=1, default=str))


def main(args: list[str] | None = None) -> int:
    """Run grid_sim: simulate the scenario once in the loop, report, and exit."""
    return spin_node(GridSimNode, args, run=lambda node, executor: node.simulate(executor))


if __name__ == '__main__':
    sys.exit(main())
