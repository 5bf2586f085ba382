"""A pytest plugin for users' own bag-replay regression tests: the `islanding_replay` fixture.

Installing the package registers it (setup.py's `pytest11` entry point), so a test needs no import::

    def test_my_bag(islanding_replay):
        result = islanding_replay('bags/my_bag')            # as fast as possible, armed, on a fresh graph
        assert result['split'] and result['cut_branch_ids'] == ['6-11']

Each call replays one bag through the four node processes, as `controlled-islanding replay BAG --fast` does, on
a ROS_DOMAIN_ID of its own (graph/rosenv.py's lock), discovery on loopback only, the ROS logs and the results
folder in the test's pytest temporary folder. Decisions and arm requests are signed with keys made for the
test session (unless CONTROLLED_ISLANDING_KEYS names the user's own), never ~/.config's. docs/nodes.md
("Replays in your own tests") lists what the result holds.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

# What a test gets unless it asks otherwise: as fast as the decisions allow, no figures (matplotlib is slow to
# import), the progress lines at debug level.
DEFAULTS = {'fast': True, 'figures': False, 'quiet': True}


@pytest.fixture
def islanding_replay(tmp_path_factory: pytest.TempPathFactory,
                     monkeypatch: pytest.MonkeyPatch) -> Iterator[Callable[..., dict]]:
    """Return `replay(bag, **options) -> summary`: one bag through a fresh node graph, its summary as a dict.

    `options` are graph.replay.replay()'s (fast, rate, arm, record, figures, estimator, timeout_s, ...), with
    DEFAULTS. The summary is summary.json's: split, status, cut_branch_ids, islands, coherent_groups, decisions,
    breaker_commands, latency_ms, results_dir (the output bag, breaker_audit.jsonl, logs/), ... A replay that
    cannot run (an unreadable bag, a node that died, no decision in time) fails the test with the reason.
    """
    from controlled_islanding.graph import GraphError
    from controlled_islanding.graph.replay import replay

    if not os.environ.get('CONTROLLED_ISLANDING_KEYS'):
        monkeypatch.setenv('CONTROLLED_ISLANDING_KEYS', str(tmp_path_factory.getbasetemp() / 'islanding_keys'))

    def run(bag: str | Path, **options: object) -> dict:
        bag = Path(bag)
        results = tmp_path_factory.mktemp(f'replay-{bag.resolve().name}') / 'results'
        try:
            return replay(bag, results, **{**DEFAULTS, 'isolate': True, **options})
        except GraphError as exc:
            pytest.fail(f'replay of {bag} failed: {exc}', pytrace=False)

    yield run
