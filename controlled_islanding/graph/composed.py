"""The node graph inside this process: fresh node objects in a fresh rclpy Context, the pipeline on one executor.

ROS 2 composition without a container: the four pipeline nodes share one SingleThreadedExecutor on a thread of
its own; the bag player and the recorder (the bag's source and the output, not the graph under test) each spin
their own executor on their own thread, as their processes would. Everything is made on entry and destroyed on
exit, context included, so a warm process (graph/worker.py) that replays bag after bag keeps only its imports and
compiled kernels: no node object, no subscription, no audit log and no DDS participant outlives a bag.

`ComposedGraph` offers what graph/replay.py's run_graph uses of a Supervisor (start, supervise, check_alive,
log_tail, restarts, hangs, cpu_s), so one replay code path drives either. Nothing is restarted: a node that
raises ends the replay with its traceback, and the process that ran it goes on with the next bag.

Being one process is also what lets a replay wait for exact conditions instead of fixed times. Every node (and an
observer that joins the Context) is one DDS participant, whose endpoints match the moment they are made, so the
graph is wired exactly when every writer has matched every reader of its topic among the nodes made (`unmatched`),
not after discovery stood still for a while. And delivery between them is synchronous (intra-process), so once
the player is done, the pipeline run until nothing is ready (`settle`) has taken every message, and each node's
diagnostics can then be read from the node itself (`diagnostics`) instead of waiting for its next publication.
"""

from __future__ import annotations

import contextlib
import importlib
import os
import threading
import time
import traceback
from collections import Counter
from collections.abc import Mapping, Sequence
from pathlib import Path

from controlled_islanding.graph import GraphError
from controlled_islanding.graph.observer import process_environment
from controlled_islanding.graph.supervisor import GRAPH, MONITOR, NodeSpec, ros_arguments

NODE_CLASSES = {'pmu_ingestion': 'PmuIngestionNode', 'coherency': 'CoherencyNode',
                'partitioning': 'PartitioningNode', 'breaker_command': 'BreakerCommandNode',
                'bag_player': 'BagPlayerNode', 'recorder': 'RecorderNode',
                'stability_monitor': 'StabilityMonitorNode'}
_PIPELINE = frozenset(spec.executable for spec in (*GRAPH, MONITOR))
_JOIN_S = 10.0  # longest wait for a thread to end at exit, s
_INFRASTRUCTURE = frozenset({'/rosout', '/parameter_events'})


class _Thread:
    """A thread that runs one harness node (player, recorder) or the pipeline, seen as a process: poll, returncode."""

    def __init__(self, name: str, target: object) -> None:
        self.name, self.returncode, self.error = name, None, ''
        self._thread = threading.Thread(target=self._run, args=(target,), name=name, daemon=True)
        self._thread.start()

    def _run(self, target: object) -> None:
        try:
            target()
            self.returncode = 0
        except GraphError as exc:  # a node that refused to start says why; no traceback
            self.error = str(exc)
            self.returncode = 1
        except Exception:
            self.error = traceback.format_exc()
            self.returncode = 1

    def poll(self) -> int | None:
        return None if self._thread.is_alive() else self.returncode

    def join(self, timeout_s: float) -> None:
        self._thread.join(timeout_s)


class ComposedGraph:
    """`with ComposedGraph(env, log_dir) as graph:` a fresh Context on env's domain; every node destroyed on exit.

    Args:
        env: The graph's environment (graph.rosenv): its ROS_DOMAIN_ID, discovery range and ROS_LOG_DIR are in
            force while the graph is open.
        log_dir: The nodes' log output (this process's stderr while the graph is open) goes to log_dir/graph.log.
        namespace: Namespace of every node, e.g. '/area1'; '' = the root one.
        remaps: Name remapping rules for every node, e.g. {'/clock': '/area1/clock'}.

    """

    def __init__(self, env: Mapping[str, str], log_dir: Path, namespace: str = '',
                 remaps: Mapping[str, str] | None = None) -> None:
        self.env, self.namespace, self.remaps = dict(env), namespace, dict(remaps or {})
        self.log_dir = Path(log_dir)
        self.restarts: list = []  # never any: nothing here is restarted
        self.hangs: list = []
        self.cpu_s: dict[str, float] = {}
        self._nodes: dict[str, object] = {}
        self._started: set[str] = set()  # every node asked for, made or still being made in its thread
        self._threads: dict[str, _Thread] = {}
        self._stopping = threading.Event()

    def __enter__(self) -> ComposedGraph:
        import rclpy
        from rclpy.executors import SingleThreadedExecutor
        from rclpy.signals import SignalHandlerOptions

        self._stack = contextlib.ExitStack()
        try:
            self.log_dir.mkdir(parents=True, exist_ok=True)
            self._redirect_stderr(self.log_dir / 'graph.log')
            self._stack.enter_context(process_environment(self.env))
            self.context = rclpy.Context()
            rclpy.init(context=self.context, domain_id=int(self.env['ROS_DOMAIN_ID']),
                       signal_handler_options=SignalHandlerOptions.NO)
            self._stack.callback(self.context.try_shutdown)
            self.executor = SingleThreadedExecutor(context=self.context)
            self._cpu0_s = time.process_time()
        except BaseException:
            self._stack.close()
            raise
        return self

    def _redirect_stderr(self, path: Path) -> None:
        # rcutils logs every node's lines to fd 2; a bag's log is its own, the caller's stderr back afterwards.
        saved = os.dup(2)
        with open(path, 'ab') as log:
            os.dup2(log.fileno(), 2)

        def restore() -> None:
            os.dup2(saved, 2)
            os.close(saved)

        self._stack.callback(restore)

    def __exit__(self, *exc_info: object) -> None:
        self._stop_pipeline()
        try:
            for thread in self._threads.values():
                thread.join(_JOIN_S)
            # A player still in a lockstep wait (the replay failed) ends when its context does.
            self.context.try_shutdown()
            for thread in self._threads.values():
                thread.join(_JOIN_S)
            self.cpu_s['composed graph (this process)'] = time.process_time() - self._cpu0_s
            for name, node in reversed(list(self._nodes.items())):
                close = getattr(node, 'close', None)
                try:
                    if close is not None:
                        close()
                    node.destroy_node()
                except Exception:  # one node's clean-up must not keep the others'
                    self._log(f'{name}: clean-up failed:\n{traceback.format_exc()}')
            self.executor.shutdown(timeout_sec=1.0)
        finally:
            self._nodes.clear()
            self._stack.close()

    def _make(self, spec: NodeSpec, overrides: Mapping[str, object] | None) -> object:
        """Make one node in this graph's Context; GraphError with the node's own words if it refuses to start."""
        from controlled_islanding.ros.params import NodeSetupError

        module = importlib.import_module(f'controlled_islanding.nodes.{spec.executable}')
        try:
            node = getattr(module, NODE_CLASSES[spec.executable])(
                context=self.context, cli_args=ros_arguments(spec, overrides, self.namespace, self.remaps))
        except NodeSetupError as exc:
            raise GraphError(f'{spec.executable} could not start: {exc}') from exc
        self._nodes[spec.executable] = node
        return node

    def start(self, spec: NodeSpec, overrides: Mapping[str, object] | None = None, name: str | None = None,
              namespace: str | None = None, prefix: Sequence[str] = (),
              remaps: Mapping[str, str] | None = None) -> _Thread | None:
        """Make one node: a pipeline node joins the shared executor, the player or the recorder gets a thread.

        Returns the player's or recorder's thread (poll, returncode, as a process), None for a pipeline node.

        Raises:
            GraphError: A pipeline node could not be made (its parameters, say), or the options ask for what a
                composed graph cannot do (another namespace per node, a prefix such as an emulated host, remaps
                of one node's own).

        """
        from rclpy.executors import SingleThreadedExecutor

        if (prefix or remaps or (namespace is not None and namespace != self.namespace)
                or name not in (None, spec.executable)):
            raise GraphError('a composed graph runs every node in this process, in one namespace, remapped alike')
        self._started.add(spec.executable)
        if spec.executable in _PIPELINE:
            try:
                self.executor.add_node(self._make(spec, overrides))
            except GraphError:
                raise
            except Exception as exc:
                raise GraphError(f'{spec.executable} could not start: {type(exc).__name__}: {exc}') from exc
            if 'pipeline' not in self._threads:
                self._threads['pipeline'] = _Thread('pipeline', self._spin_pipeline)
            return None
        if spec.executable == 'bag_player':
            from controlled_islanding.nodes.bag_player import play_once

            def play() -> None:
                executor = SingleThreadedExecutor(context=self.context)
                node = self._make(spec, overrides)
                executor.add_node(node)
                play_once(node, executor)

            thread = _Thread(spec.executable, play)
        else:
            def record() -> None:
                executor = SingleThreadedExecutor(context=self.context)
                executor.add_node(self._make(spec, overrides))
                while not self._stopping.is_set():
                    executor.spin_once(timeout_sec=0.05)

            thread = _Thread(spec.executable, record)
        self._threads[spec.executable] = thread
        return thread

    def _spin_pipeline(self) -> None:
        # No timeout: rclpy makes a timer for every wait that has one. Stopping wakes the executor.
        while not self._stopping.is_set():
            self.executor.spin_once()

    def _stop_pipeline(self) -> None:
        self._stopping.set()
        if 'pipeline' in self._threads:
            self.executor.wake()
            self._threads['pipeline'].join(_JOIN_S)

    def unmatched(self, *others: object) -> list[str]:
        """Return every endpoint not yet matched with all its peers among the nodes (and `others`); [] = wired.

        A node still being made (the player loading its bag) counts as unmatched.
        """
        missing = [f'{name} (not made yet)' for name in sorted(self._started - set(self._nodes))]
        nodes = [*self._nodes.values(), *others]
        readers: Counter[str] = Counter(s.topic_name for n in nodes for s in n.subscriptions)
        writers: Counter[str] = Counter(p.topic_name for n in nodes for p in n.publishers)
        for node in nodes:
            name = node.get_fully_qualified_name()
            missing += [f'{name} writer on {p.topic_name} ({p.get_subscription_count()} of {readers[p.topic_name]} '
                        'readers)' for p in node.publishers if p.topic_name not in _INFRASTRUCTURE
                        and p.get_subscription_count() < readers[p.topic_name]]
            missing += [f'{name} reader on {s.topic_name} ({s.get_publisher_count()} of {writers[s.topic_name]} '
                        'writers)' for s in node.subscriptions if s.get_publisher_count() < writers[s.topic_name]]
        return missing

    def made(self) -> bool:
        """Whether every node started is made (the player has loaded its bag)."""
        return self._started <= set(self._nodes)

    def node(self, name: str) -> object:
        """Return the node made for an executable (the player once it has loaded its bag).

        Raises:
            GraphError: It was not started, or is not made yet.

        """
        if name not in self._nodes:
            raise GraphError(f'{name} is not in the composed graph{" yet" if name in self._started else ""}')
        return self._nodes[name]

    def readers(self, topic: str, *others: object) -> int:
        """Return how many readers of `topic` (a full name) the nodes (and `others`) have."""
        return sum(s.topic_name == topic for n in [*self._nodes.values(), *others] for s in n.subscriptions)

    def settle(self, limit_s: float = 5.0) -> None:
        """Stop the pipeline's thread, then run its callbacks here until none is ready (at most limit_s).

        Call once the player is done: delivery in one participant is synchronous, so every message sent is
        then in a reader's queue, and a pipeline with nothing ready has taken them all.
        """
        from rclpy.executors import ShutdownException, TimeoutException

        self._stop_pipeline()
        pipeline = self._threads.get('pipeline')
        if pipeline is not None and pipeline.returncode:
            raise GraphError(f'pipeline failed in the composed graph:\n{self.log_tail("pipeline")}')
        deadline = time.monotonic() + limit_s
        idle = False
        while time.monotonic() < deadline:
            try:
                handler, _, _ = self.executor.wait_for_ready_callbacks(timeout_sec=0.0)
            except TimeoutException:
                # With a zero timeout rclpy raises this also when resumed after the wait that found work: only
                # two in a row mean that nothing is ready.
                if idle:
                    return
                idle = True
                continue
            except ShutdownException:
                return
            idle = False
            handler()
            if handler.exception() is not None:
                raise GraphError(f'a pipeline callback failed after the play: {handler.exception()!r}')

    def diagnostics(self) -> dict[str, dict[str, str]]:
        """Return each pipeline node's diagnostics now, named as an observer of /diagnostics names them.

        Only after `settle`: the pipeline's callbacks must not run meanwhile.
        """
        out = {}
        for name in _PIPELINE & set(self._nodes):
            for status in self._nodes[name].diag.statuses():
                out[status.name[len(self.namespace):]] = {kv.key: kv.value for kv in status.values}
        return out

    def _log(self, text: str) -> None:
        with open(self.log_dir / 'graph.log', 'a') as log:
            log.write(text + '\n')

    def supervise(self, heartbeats_s: Mapping[str, float] | None = None) -> list:
        """Raise if the pipeline's executor stopped (a node's callback raised); nothing is restarted."""
        self.check_alive(['pipeline'])
        return []

    def check_alive(self, names: Sequence[str] | None = None) -> None:
        """Raise if a thread of the graph ended with an error (the player ending well is not one).

        Raises:
            GraphError: Names it, with its traceback.

        """
        for name, thread in self._threads.items():
            if (names is None or name in names) and thread.poll() is not None and (
                    thread.returncode != 0 or name == 'pipeline'):
                raise GraphError(f'{name} failed in the composed graph:\n{self.log_tail(name)}')

    def log_tail(self, name: str, lines: int = 15) -> str:
        """Return a thread's traceback, else the last lines of the graph's log."""
        thread = self._threads.get(name)
        if thread is not None and thread.error:
            return thread.error.rstrip()
        path = self.log_dir / 'graph.log'
        return '\n'.join(path.read_text(errors='replace').splitlines()[-lines:]) if path.exists() else ''
