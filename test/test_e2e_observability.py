"""Partial observability on the real graph: a generator whose PMU never reports is decided unconstrained."""

from __future__ import annotations

import uuid
from pathlib import Path

import pytest

from controlled_islanding.graph.replay import replay
from controlled_islanding.sim.manifest import default_bag
from controlled_islanding.wire import topics
from controlled_islanding.wire.bagdata import load_bag

pytestmark = [pytest.mark.ros, pytest.mark.slow]

REPO = Path(__file__).resolve().parents[1]


def without_pmu(source: Path, out: Path, generator: str, bus: int) -> None:
    """Copy a bag, dropping from every PMU frame the channel that measures one generator."""
    from rosbags.highlevel import AnyReader
    from rosbags.rosbag2 import StoragePlugin, Writer

    from controlled_islanding.ros.endpoints import qos_for
    from controlled_islanding.wire.bagmeta import qos_profile
    from controlled_islanding.wire.interfaces import typestore

    store = typestore()
    with AnyReader([source], default_typestore=store) as reader, \
            Writer(out, version=9, storage_plugin=StoragePlugin.MCAP) as writer:
        conns = {c.id: writer.add_connection(c.topic, c.msgtype, msgdef=c.msgdef.data, rihs01=c.digest,
                                             offered_qos_profiles=[qos_profile(qos_for(c.topic))])
                 for c in reader.connections}
        for conn, stamp, raw in reader.messages():
            if conn.topic == topics.PMU_FRAMES:
                frame = store.deserialize_cdr(raw, conn.msgtype)
                # A machine's own channel is named '<station>/<generator>'; a bus with one machine has one channel.
                frame.measurements = [m for m in frame.measurements
                                      if not (m.station_id.endswith(f'/{generator}') or
                                              (m.bus == bus and '/' not in m.station_id))]
                raw = store.serialize_cdr(frame, conn.msgtype)
            writer.write(conns[conn.id], stamp, raw)


def test_a_generator_without_a_pmu_from_the_first_frame_is_decided_unconstrained(tmp_path):
    entry = default_bag()
    source = REPO / 'bags' / entry['bag']
    grid = load_bag(source).grid
    truth = entry['truth_groups']
    assert len(truth) > 1, 'the default bag must split'
    # The smallest machine of the largest true group: losing it must not change which groups exist.
    caps = {g.name: g.p_max_mw for g in grid.generators}
    largest = max(truth, key=len)
    victim = min(largest, key=lambda n: (caps[n], n))
    bus = next(g.bus for g in grid.generators if g.name == victim)
    bag = tmp_path / f'{entry["bag"]}_without_{victim}'
    without_pmu(source, bag, victim, bus)

    summary = replay(bag, REPO / 'build' / 'test_e2e' / f'unobserved-{uuid.uuid4().hex[:8]}', fast=True,
                     figures=False, quiet=True)
    assert summary['status'] == 'SPLIT', summary.get('status_detail')
    assert summary['coherent_groups']['unobserved'] == [victim]
    observed_truth = {frozenset(n for n in grp if n != victim) for grp in truth} - {frozenset()}
    assert {frozenset(g) for g in summary['coherent_groups']['groups']} == observed_truth
    island_of_bus = {b: isl['island'] for isl in summary['islands'] for b in isl['buses']}
    assert summary['unobserved_generators'] == {victim: island_of_bus[bus]}
    opened = {c['branch_id'] for c in summary['breaker_commands'] if c['action'] == 'open'}
    assert opened == set(summary['cut_branch_ids'])
    assert summary['restarts'] == [] and summary['hangs'] == []
