"""The testbed's report: a table row per scenario and run, why each island was lost, and docs/testbed.md."""

from __future__ import annotations

import math
import os
import shutil
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from controlled_islanding import atomic


def _fmt(x: Any, spec: str) -> str:
    return '-' if x is None else format(x, spec)


def clip(text: str, width: int) -> str:
    """Return text cut to at most width characters at a word boundary, '...' marking the cut."""
    if len(text) <= width:
        return text
    head = text[:width - 4]
    return head[:head.rfind(' ')].rstrip(';,') + ' ...' if ' ' in head else head + ' ...'


def served_text(run: dict) -> str:
    """Return a run's load served as a table cell: MW (% of the pre-fault load), or its simulation failure."""
    if run.get('simulation_failed'):
        return 'simulation failed at ' + run['simulation_failed'].split(' at ', 1)[1].split(':', 1)[0]
    if run.get('load_served_mw') is None:  # a result written before load served was recorded
        return '-'
    return f'{run["load_served_mw"]:.0f} ({run["load_served_pct"]:.1f} %)'


def table_rows(results: list[dict], reason_width: int | None = 80) -> list[list[str]]:
    """Return one row per scenario and run: the comparison table (reasons clipped at a word, or in full)."""
    rows = []
    for r in results:
        for label in ('no action', 'dtw', 'milp'):
            run = r['runs'].get(label)
            if run is None:
                continue
            isl = run['islands']
            ok = sum(1 for i in isl if i['survived'])
            why = '; '.join(w for i in isl for w in i['why_not'])
            if run.get('simulation_failed'):
                verdict = f'? (undetermined: {run["simulation_failed"]})'
            else:
                verdict = f'{ok}/{len(isl)}' + ('' if ok == len(isl) else f' ({why})')
            lost = run['load_lost_mw']
            rows.append([r['scenario'], label, ', '.join(run['cut_branch_ids']) or 'none', served_text(run),
                         verdict if reason_width is None else clip(verdict, reason_width),
                         f'{"-" if lost is None else format(lost, ".0f")} ({run["shed_mw"]:.0f} shed)',
                         f'{run.get("rejected_mw", 0.0):.0f}',
                         f'{run["f_nadir_hz"]:.2f} / {run["f_peak_hz"]:.2f}', f'{run["v_min_pu"]:.3f}',
                         _fmt(run['request_to_opening_s'], '.3f')])
    return rows


def _span(span: list[float] | None) -> str:
    return f'{span[0]:+.3f} to {span[1]:+.3f} s' if span else ''


def failure_text(isl: dict) -> str:
    """Return what failed in a lost island and when, s after the cut (from its assessment, closed_loop.assess)."""
    gens = isl['generators']
    head = f'island {isl["island"]} ({", ".join(gens[:3])}{", ..." if len(gens) > 3 else ""}'
    head += f'; rejected {", ".join(isl["rejected"])})' if isl.get('rejected') else ')'
    if 'f_outside_s' not in isl:  # a result written before the timings were recorded
        return f'{head}: {"; ".join(isl["why_not"])}'
    out = []
    if isl['generators'] and isl['rejected'] and len(isl['rejected']) == len(isl['generators']):
        out.append(f'every machine tripped by generation rejection (island load {isl["load_mw"]:.0f} MW)')
    if not isl['coherent']:
        out.append(f'machines {isl["max_pair_swing_rad"]:.2f} rad apart')
    if isl['f_outside_s']:
        since = isl['f_outside_since_s']
        out.append(f'frequency {isl["f_nadir_hz"]:.2f}..{isl["f_peak_hz"]:.2f} Hz, out of band '
                   f'{_span(isl["f_outside_s"])}' + ('' if since is None else f', already out at the cut (since '
                                                                                f'{since:+.3f} s)'))
    if isl['v_outside_s']:
        out.append(f'voltage {isl["v_min_pu"]:.3f}..{isl["v_max_pu"]:.3f} pu, out of band '
                   f'{_span(isl["v_outside_s"])}, worst at bus {isl["v_worst_bus"]}')
    if isl['machines_tripped']:
        out.append(f'machines tripped: {", ".join(isl["machines_tripped"])}')
    return f'{head}: {"; ".join(out)}'


def failure_lines(results: list[dict]) -> list[str]:
    """Return a line per lost island of every closed-loop run, and of a MILP run whose cut differs."""
    out = []
    for r in results:
        for label in ('dtw', 'milp'):
            run = r['runs'].get(label)
            if run is None or (label == 'milp' and run.get('label', '').startswith('milp (same cut')):
                continue
            if run.get('simulation_failed'):
                out.append(f'- {r["scenario"]} `{label}`: {run["simulation_failed"]}; its islands are undetermined, '
                           'none counted lost.')
                continue
            for isl in run['islands']:
                if isl['survived'] is False:
                    out.append(f'- {r["scenario"]} `{label}` {failure_text(isl)}.')
    return out


HEADER = ['scenario', 'run', 'cut', 'load served MW (% pre-fault)', 'islands survived', 'load lost MW',
          'generation tripped MW', 'f nadir / peak Hz', 'V min pu', 'request -> opening s']


def render(results: list[dict]) -> str:
    """Return the readable report: each decision, its commands, and the comparison table."""
    lines = []
    for r in results:
        d = r['decision']
        lines.append(f'{r["scenario"]}:')
        if d is None:
            lines.append('  no decision came')
        else:
            cut = f', cut {", ".join(d["cut_branch_ids"])}' if d['split'] else ''
            lines.append(f'  decision: {d["status"]}{cut}')
            for c in d['breaker_commands']:
                lines.append(f'  command {c["action"]} {c["breaker_id"]} ({c["branch_id"]})')
        for e in r['events']:
            if e['what'] in ('command', 'switching event', 'opened', 'shed scheduled'):
                lines.append('  ' + ', '.join(f'{k}={v:.3f}' if isinstance(v, float) else f'{k}={v}'
                                              for k, v in e.items()))
        loop = r['runs'].get('dtw', r['closed_loop'])
        if loop.get('simulation_failed'):
            lines.append(f'  {loop["simulation_failed"]} (undetermined, not counted as load lost)')
        if loop.get('remedy'):
            lines.append(f'  remedy: {loop["remedy"]}')
        for isl in loop['islands']:
            verdict = ('survived' if isl['survived'] else 'undetermined' if isl['survived'] is None
                       else 'LOST: ' + '; '.join(isl['why_not']))
            lines.append(f'  island {isl["island"]} ({", ".join(isl["generators"])}): {verdict}')
    widths = [max(len(h), *(len(row[i]) for row in table_rows(results))) for i, h in enumerate(HEADER)] \
        if results else [len(h) for h in HEADER]
    lines.append('')
    lines.append('  '.join(h.ljust(w) for h, w in zip(HEADER, widths, strict=True)))
    for row in table_rows(results):
        lines.append('  '.join(c.ljust(w) for c, w in zip(row, widths, strict=True)))
    return '\n'.join(lines)


def markdown(results: list[dict], args: Any, figures: list[Path], page: Path, cmd: str) -> str:
    """Return the Markdown page of the table (docs/testbed.md).

    Args:
        results: The scenarios' results.
        args: The run's settings (graph.testbed.TestbedSettings, or what --render was given).
        figures: The figures the page shows.
        page: Where the page goes (figure links are relative to it).
        cmd: The command line that made the page, quoted at its top.

    """
    out = ['# Closed-loop testbed results', '',
           f'Generated by `{cmd}` on {datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")}; do not edit by hand.', '',
           'Each scenario ran three times in ANDES: `dtw` is the closed loop (grid_sim and the four nodes, the '
           'decision commanded by breaker_command and executed in the running simulation), `no action` the same '
           'scenario untouched, `milp` the exact minimum-disruption cut for the same generator groups opened at '
           'the same time. Rules (controlled_islanding/sim/closed_loop.py): an island survives when its machines '
           "stay within pi rad of each other (relative to the cut), its frequency within 0.9633..1.03 pu of the "
           "case's nominal frequency (57.8..61.8 Hz at 60 Hz, 48.17..51.5 Hz at 50 Hz: NERC PRC-024's limits, per "
           'unit), its bus '
           'voltages within 0.8..1.2 pu from 0.5 s after the cut, and no machine trips. Load lost = load shed + '
           "the load of every island that did not survive. Generation tripped: in every island whose machines' "
           'pre-fault output exceeds its load after the shed by more than 5 % of that load, machines are tripped at '
           'the time of the shed, largest output first, each only if it fits in the remaining surplus '
           '(closed_loop.generation_to_reject; a rejected machine is not judged after its trip); the `milp` row '
           'gets the same rule. `no action` is judged as one island over the same '
           f'window. Breaker operating time {args.breaker_operating_s} s, load shed {args.shed_delay_s} s after '
           f'the opening, simulated at least {args.run_after_s} s past the request.'
           + ('' if getattr(args, 'trigger', 'scenario') == 'scenario' else
              " The request is not the scenario's: grid_sim's out-of-step trigger made it, at the first step where "
              "the measured rotor angles (the graph's /rotor_angles, against the first received) showed two machines "
              'more than 90 deg apart with no PMU voltage below 0.5 pu (closed_loop.out_of_step); an answer that '
              'does not split re-arms it, and it asks again on newer angles while that holds (at most 20 requests); '
              'the baselines answer the last request.'), '',
           '| ' + ' | '.join(HEADER) + ' |', '|' + '---|' * len(HEADER)]
    out += ['| ' + ' | '.join(row) + ' |' for row in table_rows(results)]
    out += ['', 'Reading the table:',
            '- An island with a surplus no machine fits in (each is larger than the surplus) keeps it: tripping one '
            "would leave a deficit nobody sheds, so such an island can speed up past the band's top (61.8 Hz at "
            '60 Hz) and count as lost. Overspeed protection is modelled at 1.10 pu speed (66 Hz at 60 Hz, '
            "closed_loop.py): a machine past it is listed among the machines tripped, its time among the run's "
            'actions. It is recorded, not switched off in ANDES (which stopped converging when it was, on PJM 5-bus '
            "and Kundur), and it decides no verdict: the band's top is lower.",
            '- "V min" is ANDES\' voltage variable. Zero or negative voltages in islands right after an opening '
            'were a solver artefact, not a collapse: ANDES solves the network in polar power-balance form, where '
            'V = 0 (or V < 0 with the angle off by pi) satisfies a bus trivially, and Newton started from the '
            'voltages of a large swing landed there. The solver now starts each new island from the pre-fault '
            "voltages turned with its machines' mean rotor-angle advance (GridRun._warm_start), and restarts a bus "
            "still left at 0 V next to a live one from that neighbour's voltage (listed as 'solver reseed' among "
            "the actions); only the starting point changes, not the equations. A bus left with no in-service "
            "branch (an island of one bus) is outside ANDES' network equations: its voltage, and the machine on "
            'it, are not physical (IEEE 14: G1 alone on bus 1 has shown -60, 35 and -708042 pu, and ANDES once '
            'stopped converging 2 s after such a cut), and such an island is '
            'lost by definition once its machine is rejected. '
            "Per-island figures are in each scenario's result.json in the results folder.",
            "- The lockstep opening time is request + the graph's wall latency + the breaker time, so it varies "
            'by tens of ms between runs; outcomes that change across the g6g7 variants with the same physics show '
            'how sensitive a late cut is to it.',
            '- Why islands were lost (diagnosed 2026-12-01 from the per-island timings below and, for IEEE 39 G6-G7 '
            "and case 2 G3, the exciter outputs recorded through GridRun.run's hook): (1) the machines of the island "
            'were already outside the frequency band at the cut, accelerated by the fault or slipping poles since '
            'before the request, so nothing done after the cut caused it (IEEE 39 G6 and G7 from about 5.9 s, '
            'before the 7.0 s request and after the 5.37 s first slip; Kundur area 2 from 1.53 s, before its '
            '1.567 s request, in a run with the steady-state rotor angles that split it). '
            "(2) After a late cut the slip's voltage dips have driven the exciters up (G6 and G7 at 3.5-3.9 pu "
            'field at the 7.08 s cut, G3 of case 2 at its 6.0 pu ceiling at 8.09 s), and the field winds down over '
            "2 s or more: the island's voltage rises to 1.30 pu (G6-G7, G7 alone after G6's rejection) and 1.80 pu "
            '(G3). The load, constant impedance in ANDES, grows with the square of that voltage: about 840 MW '
            "from G7's 580 MW, so that island's frequency falls to 58.2 Hz. The out-of-step trigger "
            '(docs/testbed_out_of_step.md) first fires at 90 deg (about 5.39 s), which can come before coherency '
            'separates the pair: its separation rule waits until the pair stops decelerating (measured on '
            "grid_sim's frames: two groups from 5.55 s with the rule of commit 19fcf7e, from 5.43 s with 63828a7's "
            'runaway test, with one flicker to two groups at 5.38 s). A trigger answered with '
            'no split used to never ask again (the page before this change: one request, nothing cut); it now '
            're-arms and asks again on newer '
            'angles until an answer splits (the line under its table lists the requests). (3) A surplus no machine '
            'fits '
            'in stays (case 2: G3, 725 MW, on 120 MW of load, about 340 MW at 1.7 pu), and that island speeds up '
            'past the band 2.5 s after the cut. (4) An island with no load whose machines the rejection rule trips '
            '(IEEE 14 G1 alone on bus 1, IEEE 39 G3 multitrip, PJM bus 4, Nordic 44 bus 6000 with its four '
            'machines) is counted as lost by definition, at 0 MW of load lost. (5) The groups were wrong (PJM 5-bus: '
            'an island whose machines slip apart) or the graph did not split. GBnetwork, in runs on a loaded '
            "machine: coherency's grouping of its 394 machines did not reach partitioning within groups_wait_s "
            '(2 s), so partitioning refused the request (REFUSED_STALE_GROUPS); other runs split it (72-73). '
            'Nordic 44 asks at the clearing instant (1.3 s), before its final groups can be told (measured '
            "2026-12-01): on ANDES' own rotor angles the separation rule splits off bus 6000's four machines alone "
            'there (1.80 rad from rest), and the three final groups appear only from 1.60 s; the steady-state '
            "estimates, whose fault-on error hides part of that lead (1.51 rad, below the rule's pi/2), keep one "
            "group, on grid_sim's frames and the recorded bag's alike (they agree within 0.01 rad of rotor angle "
            'since fbd1a33, 0.08 rad before); the same fault cleared 30 ms earlier, which stays one group for 5 s (it '
            'slips at 6.9 s, into other groups), is split the same way 30 ms after its clearing, so a split there '
            'is no evidence yet. Cut off alone, bus 6000 '
            'leaves the main island with the machines of buses 5300 and 6100, which slip later, and it is lost. '
            '(6) EI 33: GENROU_53 and 54 have no turbine '
            'governor in EI_33.xlsx, so their island keeps the speed it had at the cut, and whether that is '
            "inside the band depends on where in the swing the graph's latency puts the cut (lost at 62.3 Hz in a "
            'run that cut 0.41 s after the request, survived at 0.17 s). (7) IEEE 14 (both): the main island is '
            'above 1.2 pu '
            'for the first 10-60 ms of its voltage window, which starts 0.5 s after the cut but only '
            "0.3 s after its 35 % load shed. The decision's load shed and the generation rejection ran as "
            'documented in every split.', '',
            "What failed, island by island (times in s after the cut; frequency is the machines' speed, judged from "
            "the cut; voltage from 0.5 s after it; 'already out at the cut' means the island's machines left the "
            'band before the cut, so no action after the cut caused it):', '']
    out += failure_lines(results) or ['- nothing: every island of every closed-loop run survived.']
    out += ['']
    for r in results:
        fired = [e for e in r['events'] if e['what'] == 'out-of-step trigger']
        if fired:
            first, last = fired[0], fired[-1]
            out += [f'- {r["scenario"]}: the out-of-step trigger requested islanding at {first["at_s"]:.3f} s, the '
                    f'measured angles {math.degrees(first["separation_rad"]):.0f} deg apart'
                    + ('.' if len(fired) == 1 else
                       f'; answered with no split, it re-armed and asked {len(fired)} times in all, the last at '
                       f'{last["at_s"]:.3f} s ({math.degrees(last["separation_rad"]):.0f} deg).')]
    out += ['']
    for fig in figures:
        out += [f'![{fig.stem}]({os.path.relpath(fig, page.parent)})', '']
    return '\n'.join(out)


def publish(results: list[dict], args: Any, missing: list[str], *, page: Path | None, figures_dir: Path | None,
            figure_scenarios: str, cmd: str) -> None:
    """Copy the chosen figures to figures_dir and write the page (called after every scenario).

    Args:
        results: The scenarios finished so far.
        args: The run's settings, for the page's text.
        missing: Scenarios not in the table (yet), named under it.
        page: The Markdown page to write, or None.
        figures_dir: Where the figures go too, or None.
        figure_scenarios: Comma-separated scenario names whose figures go there ('': every one).
        cmd: The command line, quoted at the page's top.

    """
    figures = []
    if figures_dir is not None:
        figures_dir.mkdir(parents=True, exist_ok=True)
        chosen = {n.strip() for n in figure_scenarios.split(',') if n.strip()}
        for r in results:
            if chosen and r['scenario'] not in chosen:
                continue
            figures.append(Path(shutil.copy(r['figure'], figures_dir / Path(r['figure']).name)))
    if page is not None:
        text = markdown(results, args, figures, page, cmd)
        if missing:
            text += f'\nNot in this table (not run, failed, or unfinished when written): {", ".join(missing)}.\n'
        atomic.write_text(page, text)
