"""Read an islanding decision from any file the project writes it in, and say what a file is when it holds none.

- a replay or demo summary.json (graph/summary.py), or a decision of that shape (a manifest entry's
  expected_decision): its bag's scenario is the manifest's (bags/index.yaml);
- a testbed result: a scenario's result.json, or the testbed's `--json` output and testbed.json (a list of them):
  its scenario is the file its `path` names (else the manifest's of that name), its request the closed loop's;
- a bag holding IslandingDecision messages (a replay's output_bag): the last one answering a bag request; the
  scenario is that of the bag the summary.json beside it names, its request time the decision's request stamp
  from the bag's first network snapshot.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from controlled_islanding.evaluation.export import ExportError
from controlled_islanding.wire import topics


@dataclass(frozen=True)
class DecisionFile:
    """A decision and what it was made on, as far as its file says.

    Attributes:
        decision: The decision, as a summary.json holds it (split, islands, cut_branch_ids, ...).
        what: What the file is, for messages, e.g. "a testbed result of ieee14_g1_unstable".
        scenario: The scenario YAML the decision was made on, or None when the file does not say.
        request_s: The decision's request, s from the simulation start, or None (the scenario's own).

    """

    decision: dict[str, Any]
    what: str
    scenario: Path | None = None
    request_s: float | None = None


def read_decision(path: Path, scenario: str | None = None) -> DecisionFile:
    """Return the decision a file holds; `scenario` picks one of a file of several testbed results by name.

    Raises:
        ExportError: The file holds no decision ("not a decision: " and what it is), or several and none picked.

    """
    path = Path(path)
    if path.is_dir() or path.suffix in ('.mcap', '.db3'):
        return _from_bag(path)
    try:
        data = json.loads(path.read_text())
    except OSError as exc:
        raise ExportError(f'{path}: cannot read it: {exc}') from exc
    except ValueError:
        raise ExportError(f'not a decision: {path} is neither JSON nor a bag') from None
    if isinstance(data, list):
        return _from_testbed_list(path, data, scenario)
    if not isinstance(data, dict):
        raise ExportError(f'not a decision: {path} holds a JSON {type(data).__name__}, not an object')
    if _is_testbed_result(data):
        return _from_testbed_result(data, scenario)
    if 'split' in data:
        return _from_summary(data)
    raise ExportError(f'not a decision: {path} is {_what_object(data)}')


def _what_object(data: dict[str, Any]) -> str:
    """Name a JSON object that holds no decision, by the keys the project's other files have."""
    if not data:
        return 'an empty JSON object'
    if {'messages', 'bag_duration_s', 'speed_vs_real_time'} <= data.keys():
        return 'a bag player report'
    if {'request_id', 'outcome', 'events'} <= data.keys():
        return "grid_sim's report of a closed-loop run (its decision is in the scenario's result.json)"
    if {'interrupted_utc', 'finished'} <= data.keys():
        return 'the marker of an interrupted testbed run'
    return f'a JSON object with keys {", ".join(sorted(map(str, data))[:8])} (a decision has split and islands)'


def _is_testbed_result(data: Any) -> bool:
    return isinstance(data, dict) and {'scenario', 'decision', 'closed_loop'} <= data.keys()


def _from_summary(data: dict[str, Any]) -> DecisionFile:
    bag = data.get('bag')
    kind = 'a replay summary' if 'results_dir' in data else 'a decision'
    if 'results_dir' in data and data['split'] is None:
        undecided = ', '.join(data.get('undecided_requests') or []) or 'none'
        raise ExportError(f'not a decision: a replay summary of {bag} with no decision (undecided requests: '
                          f'{undecided})')
    return DecisionFile(data, f'{kind} of {bag}' if bag else kind, _manifest_scenario(bag) if bag else None)


def _from_testbed_list(path: Path, data: list[Any], scenario: str | None) -> DecisionFile:
    if not data:
        raise ExportError(f'not a decision: {path} is an empty JSON list')
    if not all(_is_testbed_result(r) for r in data):
        raise ExportError(f'not a decision: {path} is a JSON list of {len(data)} item(s) that are not all testbed '
                          'results')
    names = [str(r['scenario']) for r in data]
    if scenario is None and len(data) > 1:
        raise ExportError(f'{path} holds {len(data)} testbed results ({", ".join(names)}); give --scenario NAME')
    if scenario is not None and scenario not in names:
        raise ExportError(f'{path}: no testbed result of scenario {scenario!r} (it has {", ".join(names)})')
    return _from_testbed_result(data[names.index(scenario) if scenario is not None else 0], None)


def _from_testbed_result(data: dict[str, Any], scenario: str | None) -> DecisionFile:
    name = str(data['scenario'])
    if scenario is not None and scenario != name:
        raise ExportError(f'the testbed result is of scenario {name!r}, not {scenario!r}')
    what = f'a testbed result of {name}'
    if not data['decision']:
        raise ExportError(f'not a decision: {what} of a run with no decision')
    yaml_file = Path(str(data.get('path', '')))
    if not yaml_file.is_file():
        yaml_file = _manifest_scenario(name)
    loop = data.get('closed_loop') or {}
    return DecisionFile(data['decision'], what, yaml_file, loop.get('request_s'))


def _manifest_scenario(bag: str | None) -> Path | None:
    """Return the scenario file of the manifest entry of a bag (a path, or a name in bags/index.yaml), if any."""
    from controlled_islanding.locations import manifest_path
    from controlled_islanding.sim.manifest import entries_by_bag, entry_for_bag

    if not bag:
        return None
    bag_path = Path(bag)
    entry = entry_for_bag(bag_path) if bag_path.is_dir() else None
    if entry is not None:
        return bag_path.parent / entry['scenario']
    entry = entries_by_bag().get(bag_path.name)
    return manifest_path().parent / entry['scenario'] if entry else None


def _from_bag(path: Path) -> DecisionFile:
    from rosbags.highlevel import AnyReader

    from controlled_islanding.wire.interfaces import typestore
    from controlled_islanding.wire.messages import stamp_s

    bag = path.parent if path.is_file() else path
    try:
        with AnyReader([bag], default_typestore=typestore()) as reader:
            wanted = [c for c in reader.connections if c.topic in (topics.ISLANDING_DECISION, topics.NETWORK_SNAPSHOT)]
            decisions, t0_s = [], None
            for conn, _, raw in reader.messages(connections=wanted):
                msg = reader.deserialize(raw, conn.msgtype)
                if conn.topic == topics.NETWORK_SNAPSHOT:
                    t0_s = stamp_s(msg.header.stamp) if t0_s is None else t0_s
                elif not msg.request_id.startswith('probe-'):  # the replay's own probes, not the bag's requests
                    decisions.append(msg)
            listed = sorted({c.topic for c in reader.connections})
    except Exception as exc:  # rosbags raises assorted reader errors for what is not a bag it reads
        raise ExportError(f'not a decision: {path} is not a bag rosbags reads ({exc})') from exc
    if not decisions:
        raise ExportError(f'not a decision: a bag with no IslandingDecision on {topics.ISLANDING_DECISION} '
                          f'(its topics: {", ".join(listed) or "none"})')
    msg = decisions[-1]
    summary = bag.parent / 'summary.json'
    played = json.loads(summary.read_text()).get('bag') if summary.is_file() else None
    request_s = stamp_s(msg.request_stamp) - t0_s if t0_s is not None else None
    return DecisionFile(_message_dict(msg), f'an IslandingDecision of the bag {bag}', _manifest_scenario(played),
                        request_s)


def _message_dict(msg: Any) -> dict[str, Any]:
    """Return an IslandingDecision message as a summary.json holds a decision."""
    status = {getattr(msg, n): n.removeprefix('STATUS_') for n in dir(msg) if n.startswith('STATUS_')}
    islands = [{'island': i, 'buses': [int(b) for b, k in zip(msg.bus_numbers, msg.bus_island, strict=True) if k == i],
                'generation_mw': float(msg.island_generation_mw[i]), 'load_mw': float(msg.island_load_mw[i]),
                'shed_mw': float(msg.island_shed_mw[i])} for i in range(len(msg.island_generation_mw))]
    return {'split': bool(msg.split), 'status': status.get(int(msg.status), str(msg.status)),
            'decision_id': msg.decision_id, 'request_id': msg.request_id, 'islands': islands,
            'cut_branch_ids': list(msg.cut_branch_ids),
            'remedial_actions': {'shed_mw_by_bus': {int(b): float(mw) for b, mw in zip(msg.shed_bus, msg.shed_mw,
                                                                                      strict=True)},
                                 'trip_generators': list(msg.trip_generator_names)}}


def decision_and_case(source: DecisionFile, case: str | None = None, addfile: str | None = None,
                      outages: list[str] | None = None) -> tuple[Any, Any, str]:
    """Return the export.Decision, the ANDES System to apply it to, and where that case came from.

    Args:
        source: The decision read.
        case: A scenario YAML (its case set up as the simulator does), or a case file or a case bundled with
            ANDES taken as it is; None: the scenario the decision was made on.
        addfile: PSS/E .dyr of a .raw `case`.
        outages: Branches out when the decision was made; None: the scenario's trips before the request (none
            for a plain case file).

    Raises:
        ExportError: No case to apply it to, or the decision or case is unusable.

    """
    from controlled_islanding.evaluation import export

    if case is None and source.scenario is None:
        raise ExportError(f'{source.what}: the scenario it was made on is not known (not in bags/index.yaml); '
                          'give --case')
    decision = export.Decision.from_summary(source.decision)
    if case is not None and Path(case).suffix not in ('.yaml', '.yml'):
        ss, seen = export.load_case(case, addfile), ()
    else:
        case = str(case or source.scenario)
        ss, seen = export.scenario_case(case, source.request_s)
    return replace(decision, outages=tuple(seen if outages is None else outages)), ss, case
