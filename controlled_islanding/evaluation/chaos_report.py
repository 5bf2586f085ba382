"""The chaos sweep's report (harness/chaos_sweep.py): its tables as text and as a generated section of a page.

The section replaces whatever stands between BEGIN and END in the page (docs/nodes.md), or is added at its end.
"""

from __future__ import annotations

import statistics
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path

from controlled_islanding import atomic
from controlled_islanding.locations import checkout

BEGIN = '<!-- chaos sweep: generated, do not edit by hand -->'
END = '<!-- end of the chaos sweep -->'
KIND_NAMES = {'kill': 'kill -9', 'stop': 'SIGSTOP, SIGCONT', 'partition': 'WAN partition', 'clock_step': 'clock step'}
VERDICTS = ('commanded', 'no split', 'refused', 'not delivered', 'unheard', 'none', 'error')
REASONED = ('commanded', 'no split', 'refused', 'not delivered')


def undelivered_reason(result: dict) -> str | None:
    """Return why a split decision never reached breaker_command's audit, when the run's facts say it, else None.

    A breaker node the supervisor restarted (killed, or found hung while stopped) never executes a decision made
    before it started (the decision topic is volatile by design, and it starts disarmed); a WAN cut between control
    and substation that breaker_command reported as `control_centre_silent` kept the decision from it.
    """
    restarts = [r for r in result.get('restarts', ()) if r['name'] == 'breaker_command']
    if restarts:
        return (f'breaker_command was restarted ({restarts[0]["cause"]}) while the decision was out: a breaker node '
                'never executes a decision made before it started')
    fault = (result.get('chaos') or {}).get('fault') or {}
    if fault.get('kind') == 'partition' and '/breaker_command warn.control_centre_silent' in result.get('raised', {}):
        return 'the WAN between control and substation was cut: breaker_command reported control_centre_silent'
    return None


def verdict(result: dict) -> str:
    """Return how a run ended: one of VERDICTS ('error': the run itself could not be carried out).

    'not delivered' is a split decision breaker_command never audited for a reason the run's facts name
    (undelivered_reason); 'unheard' is one with no such reason.
    """
    if 'error' in result:
        return 'error'
    kind = result['answer']['kind']
    return 'not delivered' if kind == 'unheard' and undelivered_reason(result) else kind


def reason(result: dict) -> str:
    """Return the reason of how a run ended (the error, the refusal's, or why a decision was not delivered)."""
    if 'error' in result:
        return result['error'].splitlines()[0]
    return undelivered_reason(result) if verdict(result) == 'not delivered' else result['answer']['reason']


def reasoned(result: dict) -> bool:
    """Return whether a run ended with a decision or a reasoned refusal (the acceptance of issue 29)."""
    return verdict(result) in REASONED


def reason_class(result: dict) -> str:
    """Return a refusal's reason without its detail, e.g. 'breaker_command stale' or 'partitioning REFUSED_...'."""
    return reason(result).split(':', 1)[0]


def _cut(result: dict) -> tuple[str, ...]:
    return tuple(sorted(result.get('opened') or ()))


def opened_text(result: dict) -> str:
    """Return the branches a run opened, or 'none' and, where its cut was due only after the run ended, when."""
    opened = _cut(result)
    if opened:
        return ', '.join(opened)
    due = [e['at_s'] for e in result.get('events', ()) if e['what'] == 'switching event']
    if due:  # lockstep charges the wall time held at the request to sim time (nodes/grid_sim.py)
        return f'none: due at {min(due):.2f} s (sim), after the run ended'
    return 'none'


def _pct(x: float | None) -> str:
    return '-' if x is None else f'{x:.1f} %'


def served(r: dict) -> str:
    """Return a run's load served, % of the pre-fault load, or why there is none."""
    if 'error' in r:
        return '-'
    if r.get('simulation_failed'):
        return 'simulation failed'
    return _pct(r['load_served_pct'])


def _opening(r: dict) -> str:
    return '-' if r.get('request_to_opening_s') is None else f'{r["request_to_opening_s"]:.2f}'


def _baselines(results: list[dict]) -> dict[str, list[dict]]:
    """Return each scenario's unfaulted runs."""
    out: dict[str, list[dict]] = {}
    for r in results:
        if r['seed'] is None and 'error' not in r:
            out.setdefault(r['scenario'], []).append(r)
    return out


def _each(runs: list[dict], text: object) -> str:
    return ', '.join(text(r) for r in runs) or '-'


def summary_rows(results: list[dict]) -> list[list[str]]:
    """Return one row per system and fault kind, and one per system in all."""
    base = _baselines(results)
    runs = [r for r in results if r['seed'] is not None]
    rows = []
    for scenario in sorted({r['scenario'] for r in runs}):
        mine = [r for r in runs if r['scenario'] == scenario]
        groups = [(KIND_NAMES[k], [r for r in mine if r['chaos']['fault']['kind'] == k]) for k in KIND_NAMES]
        for label, group in [*groups, ('all', mine)]:
            if not group:
                continue
            first = not rows or rows[-1][1] == 'all'
            counts = Counter(verdict(r) for r in group)
            asked = [r for r in group if 'error' not in r and r['chaos']['recovered'] is not None]
            unfaulted = base.get(scenario, [])
            same = [r for r in group if 'error' not in r and _cut(r) in {_cut(u) for u in unfaulted}]
            pcts = [r['load_served_pct'] for r in group if 'error' not in r and not r.get('simulation_failed')]
            opening = [r['request_to_opening_s'] for r in group if r.get('request_to_opening_s') is not None]
            rows.append([scenario if first else '', label, str(len(group)),
                         f'{sum(r["chaos"]["recovered"] for r in asked)}/{len(asked)}' if asked else '-',
                         *(str(counts.get(v, 0)) for v in VERDICTS),
                         str(sum(len(r.get('unsafe', ())) for r in group)),
                         f'{len(same)}/{len(group)}',
                         (f'{len(opening)}: {statistics.median(opening):.2f} ({max(opening):.2f})' if opening
                          else '0') + f' / {_each(unfaulted, _opening)}',
                         (f'{statistics.median(pcts):.1f} % ({min(pcts):.1f}-{max(pcts):.1f})' if pcts
                          else '-') + f' / {_each(unfaulted, served)}'])
    return rows


SUMMARY_HEADER = ('system', 'fault', 'runs', 'recovered', 'commanded', 'no split', 'refused', 'not delivered',
                  'unheard', 'no decision', 'run failed', 'unsafe commands', 'same cut as an unfaulted run',
                  'opened: runs, median (max) s after the request / unfaulted runs',
                  'load served: median (range) / unfaulted runs')
RUN_HEADER = ('system', 'seed', 'fault', 'fired (s after request)', 'recovered after (s)', 'answer', 'opened',
              'load served (unfaulted)', 'unsafe', 'wall (s)')


def run_rows(results: list[dict]) -> list[list[str]]:
    """Return one row per faulted run."""
    base = _baselines(results)
    rows = []
    for r in sorted((r for r in results if r['seed'] is not None), key=lambda r: (r['scenario'], r['seed'])):
        chaos = r['chaos'] or {}
        v = verdict(r)
        answer = v if v in ('commanded', 'no split') else f'{v}: {reason(r)[:120]}'
        if 'error' not in r:
            a = r['answer']
            if len(a['answers']) > 1:
                answer += f' ({len(a["answers"])} decisions for the request)'
        fired = chaos.get('fired_after_request_s')
        rec = chaos.get('recovered')
        unfaulted = base.get(r['scenario'], [])
        rows.append([r['scenario'], str(r['seed']), chaos.get('describe', '-'),
                     '-' if fired is None else f'{fired:+.3f}',
                     '-' if rec is None else (f'{chaos["recovered_after_s"]:.1f}' if rec else 'NO'),
                     answer.replace('|', '/'), opened_text(r),
                     f'{served(r)} ({_each(unfaulted, served)})',
                     str(len(r.get('unsafe', ()))), f'{r.get("wall_s", 0):.0f}'])
    return rows


def _table(header: tuple[str, ...], rows: list[list[str]]) -> list[str]:
    return ['| ' + ' | '.join(header) + ' |', '|' + '---|' * len(header)] + ['| ' + ' | '.join(r) + ' |' for r in rows]


def figures(results: list[dict]) -> dict:
    """Return the sweep's headline figures: runs, unsafe commands, runs ending reasoned, wall time, load average."""
    runs = [r for r in results if r['seed'] is not None]
    ok = [r for r in runs if reasoned(r)]
    loads = [x for r in results for x in r.get('load_average', ())]
    return {'runs': len(runs), 'seeds': sorted({r['seed'] for r in runs}),
            'systems': sorted({r['scenario'] for r in runs}),
            'unsafe': sum(len(r.get('unsafe', ())) for r in results), 'reasoned': len(ok),
            'not_delivered': sum(verdict(r) == 'not delivered' for r in runs),
            'wall_s': sum(r.get('wall_s', 0.0) for r in results),
            'load_average': (min(loads), statistics.median(loads), max(loads)) if loads else None}


def render(results: list[dict]) -> str:
    """Return the report as text: the headline, the summary table, the refusal reasons, every run."""
    f = figures(results)
    lines = [headline(f), '', *_table(SUMMARY_HEADER, summary_rows(results)), '', *reasons(results), '',
             *_table(RUN_HEADER, run_rows(results))]
    return '\n'.join(lines)


def _hours(seconds: float) -> str:
    return f'{seconds / 60:.0f} min' if seconds < 7200 else f'{seconds / 3600:.1f} h'


def headline(f: dict) -> str:
    """Return the sweep's figures in two sentences."""
    load = f['load_average']
    s = f['seeds']
    seeds = (f'seeds {s[0]}-{s[-1]}' if s and s == list(range(s[0], s[-1] + 1))
             else 'seeds ' + ', '.join(map(str, s)))
    return (f'{f["runs"]} seeded runs ({seeds}) on {len(f["systems"])} systems, one fault each: '
            f'{f["unsafe"]} unsafe commands; {f["reasoned"]} of {f["runs"]} ended with a decision or a reasoned '
            'refusal' + (f' ({f["not_delivered"]} of them a split decision that did not reach breaker_command, '
                         'for the reason given)' if f['not_delivered'] else '')
            + f'. Wall time {_hours(f["wall_s"])} in all (the unfaulted runs included)'
            + (f', 1-minute load average {load[0]:.1f} to {load[2]:.1f} (median {load[1]:.1f}) when the runs began '
               'and ended.' if load else '.'))


def reasons(results: list[dict]) -> list[str]:
    """Return the refusal reasons and how many runs ended with each, and the runs that ended otherwise."""
    runs = [r for r in results if r['seed'] is not None]
    counts = Counter(reason_class(r) for r in runs if verdict(r) == 'refused')
    out = ['Refusals by reason:' if counts else 'No refusals.']
    out += [f'- {reason}: {n}' for reason, n in counts.most_common()]
    for title, kinds in (('Split decisions that did not reach breaker_command:', ('not delivered',)),
                         ('Runs that ended without a decision or a reasoned refusal:', ('unheard', 'none', 'error'))):
        odd = [r for r in runs if verdict(r) in kinds]
        if odd:
            out += ['', title] + [f'- {r["scenario"]} seed {r["seed"]} ({(r["chaos"] or {}).get("describe", "-")}): '
                                  f'{reason(r)}' for r in odd]
    bystanders = [(r, x) for r in results for x in r.get('restarts', ())
                  if x['name'] != ((r.get('chaos') or {}).get('fault') or {}).get('target')]
    out += ['', f'Restarts of a node the fault did not touch (the unfaulted runs included): {len(bystanders)}.']
    out += [f'- {r["scenario"]} seed {r["seed"]}: {x["name"]} ({x["reason"]})' for r, x in bystanders]
    unsafe = [(r, u) for r in results for u in r.get('unsafe', ())]
    if unsafe:
        out += ['', 'Unsafe commands:'] + [f'- {r["scenario"]} seed {r["seed"]}: {u}' for r, u in unsafe]
    return out


def section(results: list[dict], cmd: str, settings_text: str, invocations: list[dict]) -> str:
    """Return the generated Markdown section, from BEGIN to END; `invocations` says how the sweep was run."""
    f = figures(results)
    root = checkout()
    # Paths inside the checkout as the page's reader would type them there.
    here = (lambda text: text.replace(f'{root}/', '')) if root else (lambda text: text)
    ran = [f'`{here(i["command"])}` from {i["begun_utc"]} to {i["ended_utc"]} ({_hours(i["wall_s"])}, '
           f'{i["runs"]} runs, load average {i["load_average"][0]:.1f} then {i["load_average"][1]:.1f})'
           for i in invocations if i['runs']]
    return '\n'.join([
        BEGIN,
        f'Generated by `{here(cmd)}` on {datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")} (code: '
        '`controlled_islanding/harness/chaos_sweep.py`, `controlled_islanding/evaluation/chaos_report.py`).'
        + (' The sweep ran as ' + '; '.join(ran) + '.' if ran else ''), '',
        f'**{headline(f)}** {settings_text}', '',
        *_table(SUMMARY_HEADER, summary_rows(results)), '', *reasons(results), '',
        '<details><summary>Every run</summary>', '', *_table(RUN_HEADER, run_rows(results)), '', '</details>',
        END])


def write_section(page: Path, text: str) -> None:
    """Put the section into the page, in place of the one there, else at its end."""
    old = page.read_text() if page.exists() else ''
    if BEGIN in old and END in old:
        head, rest = old.split(BEGIN, 1)
        new = head + text + rest.split(END, 1)[1]
    else:
        new = old.rstrip('\n') + '\n\n' + text + '\n'
    atomic.write_text(page, new)
