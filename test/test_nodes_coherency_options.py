"""The coherency node's DTW options reach the core, on a real pmu_ingestion -> coherency pair over DDS."""

from __future__ import annotations

import pytest
from controlled_islanding_msgs.msg import CoherentGroups, NetworkSnapshot, PmuFrame
from nodes_harness import graph
from test_nodes_bad_input import bag_messages

from controlled_islanding.graph.supervisor import GRAPH
from controlled_islanding.sim.manifest import manifest_entries
from controlled_islanding.wire import topics

pytestmark = [pytest.mark.ros, pytest.mark.slow]

NODES = [s for s in GRAPH if s.executable in ('pmu_ingestion', 'coherency')]


@pytest.mark.parametrize(('options', 'decimate', 'all_pairs'), [
    ({}, '1', False),
    ({'dtw_decimate_to_fps': 10.0, 'dtw_all_pairs': True}, '6', True),
])
def test_decimation_and_all_pairs_reach_the_core(options, decimate, all_pairs):
    if not manifest_entries():
        pytest.skip('no bags in bags/index.yaml')
    snapshot, frames = bag_messages()  # the default bag's first 2 s at 60 frames/s, before its fault: no split
    overrides = {'coherency': {'min_samples': 30, **options}}
    with graph(f'test_nodes_coherency_options_{decimate}', [(s, overrides.get(s.executable, {})) for s in NODES]) \
            as (sup, probe):
        probe.publisher(NetworkSnapshot, topics.NETWORK_SNAPSHOT)
        probe.publisher(PmuFrame, topics.PMU_FRAMES)
        groups = probe.collect(CoherentGroups, topics.COHERENT_GROUPS)
        probe.wait_matched(topics.NETWORK_SNAPSHOT, 2)
        probe.wait_matched(topics.PMU_FRAMES, 1)
        probe.wait_wired(('pmu_ingestion', 'coherency'))
        probe.pubs[topics.NETWORK_SNAPSHOT].publish(snapshot)
        probe.spin_for(0.5)
        for frame in frames:
            probe.pubs[topics.PMU_FRAMES].publish(frame)
            probe.spin_for(0.005)
        assert probe.spin_until(lambda: any(len(g.generator_names) > 1 for g in groups), 20.0), 'no grouping'
        assert probe.spin_until(lambda: probe.diagnostics.get('coherency', {}).get('dtw_decimate') == decimate, 5.0), \
            probe.diagnostics.get('coherency')
        last = [g for g in groups if len(g.generator_names) > 1][-1]
        n = len(last.generator_names)
        assert last.k == 1, 'the window before the fault splits nothing'
        # Without all pairs, a window the separation rule does not split needs no DTW, so none is published.
        assert len(last.distance) == (n * n if all_pairs else 0)
        sup.check_alive()
