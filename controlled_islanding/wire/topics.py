"""Topic names shared by the nodes, the simulator and the tools.

The constants are the names in the root namespace: what bags record, what the docs show, and what a graph
started without a namespace uses. Nodes create every publisher and subscription with `relative(name)`, a
name resolved in the node's namespace, so `--ros-args -r __ns:=/area1` moves a node's whole interface
(/area1/pmu/frames, ...) and two control areas can run side by side on one domain. /clock, /diagnostics and
/rosout stay global, as ROS tools expect them (a graph that needs its own clock remaps /clock, as
`replay --namespace` does).
"""

PMU_FRAMES = '/pmu/frames'
NETWORK_SNAPSHOT = '/network/snapshot'
BRANCH_STATUS = '/network/branch_status'
ISLANDING_REQUEST = '/islanding/request'
ROTOR_ANGLES = '/rotor_angles'
COHERENT_GROUPS = '/coherent_groups'
ISLANDING_DECISION = '/islanding/decision'
BREAKER_COMMANDS = '/breaker/commands'
DIAGNOSTICS = '/diagnostics'
CLOCK = '/clock'

TRUTH_ROTOR_ANGLES = '/truth/rotor_angles'
TRUTH_COHERENT_GROUPS = '/truth/coherent_groups'
TRUTH_TOPICS = (TRUTH_ROTOR_ANGLES, TRUTH_COHERENT_GROUPS)

GLOBAL = frozenset({CLOCK, DIAGNOSTICS, '/rosout', '/parameter_events'})


def relative(topic: str) -> str:
    """Return the name a node uses for a root-namespace topic: relative, except the global ones."""
    return topic if topic in GLOBAL else topic.lstrip('/')


def in_namespace(topic: str, namespace: str) -> str:
    """Return the fully qualified name a root-namespace topic has in a namespace ('' or '/area1', ...)."""
    if topic in GLOBAL or not namespace.strip('/'):
        return topic
    return f'/{namespace.strip("/")}/{relative(topic)}'
