"""Topic names shared by the nodes, the simulator and the tools."""

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
