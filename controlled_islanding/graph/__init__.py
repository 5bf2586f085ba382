"""The node graph as processes: start, supervise and stop them, give them a ROS environment, observe them.

Replays of a bag (replay, suite) and closed-loop testbed runs (testbed) are orchestrated here; every failure
of a graph is a GraphError, which the commands turn into an exit status.
"""


class GraphError(RuntimeError):
    """A graph could not be run or did not answer: a node died, a bag is unreadable, a wait ran out."""
