"""breaker_command: turn islanding decisions into breaker open commands, under an arm switch and an audit log.

Rules, in the order they are checked for each decision (the first that fails refuses the whole decision,
because opening only some of the cut lines does not form the intended islands):
1. a decision id is executed at most once (a repeat is refused as 'duplicate');
2. the decision must be well formed and stamped, and not older than `max_decision_age_s` on this node's clock;
3. the node must be armed (SetArmed service; `armed` parameter at start);
4. every cut branch must map to a breaker in `breakers_file`.
Every command and every refusal is appended to `audit_log` as one JSON line and fsync'ed BEFORE the command
is published, so the log never misses a command that reached the field.
"""

from __future__ import annotations

import json
import os
import sys
import time
from pathlib import Path

import yaml
from controlled_islanding_msgs.msg import BreakerCommand, IslandingDecision
from controlled_islanding_msgs.srv import SetArmed
from rclpy.node import Node

from controlled_islanding import topics
from controlled_islanding.messages import stamp_s
from controlled_islanding.node_common import Diagnostics, NodeSetupError, qos_for, spin_node
from controlled_islanding.supervisor import config_dir


def load_breaker_map(path: str | Path) -> dict[str, str]:
    """Read a breakers file: a YAML mapping `breakers: {branch_id: breaker_id}`.

    Raises:
        NodeSetupError: The file is missing, not YAML, or not a mapping of strings.

    """
    try:
        data = yaml.safe_load(Path(path).read_text())
    except (OSError, yaml.YAMLError) as exc:
        raise NodeSetupError(f'breakers_file {path}: {exc}') from exc
    table = data.get('breakers') if isinstance(data, dict) else None
    if not isinstance(table, dict) or not table:
        raise NodeSetupError(f'breakers_file {path}: expected a non-empty mapping under "breakers:"')
    return {str(k): str(v) for k, v in table.items()}


class AuditLog:
    """Append-only JSON-lines file; every record is fsync'ed before append() returns."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fd = os.open(self.path, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)

    def append(self, record: dict) -> None:
        """Write one record as a JSON line and fsync it."""
        os.write(self._fd, (json.dumps(record, sort_keys=True) + '\n').encode())
        os.fsync(self._fd)

    def close(self) -> None:
        """Close the file."""
        os.close(self._fd)


class BreakerCommandNode(Node):
    """Executes islanding decisions as breaker commands, at most once each, only while armed."""

    def __init__(self) -> None:
        super().__init__('breaker_command')
        self.declare_parameter('breakers_file', '')
        self.declare_parameter('audit_log', 'breaker_audit.jsonl')
        self.declare_parameter('armed', False)
        self.declare_parameter('max_decision_age_s', 1.0)
        breakers_file = self.get_parameter('breakers_file').value
        if not breakers_file:
            raise NodeSetupError('parameter breakers_file is empty; it must name a YAML branch -> breaker map')
        if not Path(breakers_file).is_absolute():
            breakers_file = config_dir() / breakers_file
        self.breakers = load_breaker_map(breakers_file)
        self.max_age_s = float(self.get_parameter('max_decision_age_s').value)
        self.armed = bool(self.get_parameter('armed').value)
        self.audit = AuditLog(self.get_parameter('audit_log').value)
        self.seen: set[str] = set()
        self.diag = Diagnostics(self)
        self.diag.values['armed'] = str(self.armed)
        self.pub = self.create_publisher(BreakerCommand, topics.BREAKER_COMMANDS, qos_for(topics.BREAKER_COMMANDS))
        self.create_subscription(IslandingDecision, topics.ISLANDING_DECISION, self.on_decision,
                                 qos_for(topics.ISLANDING_DECISION))
        self.create_service(SetArmed, '~/set_armed', self.on_set_armed)
        self.get_logger().info(f'{len(self.breakers)} breakers mapped, armed={self.armed}, audit={self.audit.path}')

    def _record(self, event: str, decision: IslandingDecision | None = None, **fields: str) -> None:
        record = {'event': event, 'wall_time_s': time.time(), 'ros_time_s': self.get_clock().now().nanoseconds * 1e-9}
        if decision is not None:
            record.update(decision_id=decision.decision_id, request_id=decision.request_id)
        record.update(fields)
        self.audit.append(record)

    def on_set_armed(self, request: SetArmed.Request, response: SetArmed.Response) -> SetArmed.Response:
        """Arm or disarm; audited."""
        self.armed = bool(request.armed)
        self.diag.values['armed'] = str(self.armed)
        self._record('armed' if self.armed else 'disarmed')
        response.armed = self.armed
        response.message = 'armed: decisions will be executed' if self.armed else 'disarmed: nothing is commanded'
        self.get_logger().info(response.message)
        return response

    def _refuse(self, decision: IslandingDecision, reason: str, detail: str) -> None:
        self._record('refusal', decision, reason=reason, detail=detail)
        self.diag.reject(reason, f'decision {decision.decision_id!r}: {detail}')

    def _check(self, decision: IslandingDecision) -> tuple[str, str] | None:
        if not decision.decision_id:
            return 'empty_message', 'decision_id is empty'
        if decision.decision_id in self.seen:
            return 'duplicate', 'already handled; a decision is executed at most once'
        n = len(decision.cut_branch_ids)
        if len(decision.cut_from_bus) != n or len(decision.cut_to_bus) != n:
            return 'array_length', (f'{n} cut_branch_ids but {len(decision.cut_from_bus)} cut_from_bus and '
                                    f'{len(decision.cut_to_bus)} cut_to_bus')
        if decision.split and n == 0:
            return 'empty_message', 'split is true but there are no cut branches'
        made_s = stamp_s(decision.header.stamp)
        if made_s <= 0.0:
            return 'missing_stamp', 'header.stamp is zero'
        age_s = self.get_clock().now().nanoseconds * 1e-9 - made_s
        if age_s > self.max_age_s:
            return 'stale', f'made {age_s:.3f} s ago, more than max_decision_age_s={self.max_age_s}'
        if age_s < -self.max_age_s:
            return 'time_backwards', f'stamped {-age_s:.3f} s in the future of this node clock'
        return None

    def on_decision(self, decision: IslandingDecision) -> None:
        """Validate a decision and, when armed and valid, command and audit each cut breaker."""
        t0 = time.perf_counter()
        self.diag.arrived()
        problem = self._check(decision)
        if problem is None or problem[0] != 'duplicate':
            self.seen.add(decision.decision_id)
        if problem is not None:
            self._refuse(decision, *problem)
            return
        if not decision.split:
            self._record('no_split', decision)
            return
        if not self.armed:
            self._refuse(decision, 'not_armed', 'node is disarmed; call ~/set_armed to arm it')
            return
        unknown = [b for b in decision.cut_branch_ids if b not in self.breakers]
        if unknown:
            self._refuse(decision, 'unknown_breaker', f'no breaker mapped for branches {", ".join(unknown)}')
            return
        stamp = self.get_clock().now().to_msg()
        for branch_id in decision.cut_branch_ids:
            breaker_id = self.breakers[branch_id]
            command = BreakerCommand(command_id=f'{decision.decision_id}/{breaker_id}',
                                     decision_id=decision.decision_id, breaker_id=breaker_id, branch_id=branch_id,
                                     action=BreakerCommand.ACTION_OPEN)
            command.header.stamp = stamp
            self._record('command', decision, command_id=command.command_id, breaker_id=breaker_id,
                         branch_id=branch_id, action='open')
            self.pub.publish(command)
        self.diag.computed(time.perf_counter() - t0)
        self.get_logger().info(f'decision {decision.decision_id}: opened {len(decision.cut_branch_ids)} breakers')

    def close(self) -> None:
        """Close the audit log."""
        self.audit.close()


def main(args: list[str] | None = None) -> int:
    """Run the breaker_command node."""
    return spin_node(BreakerCommandNode, args)


if __name__ == '__main__':
    sys.exit(main())
