"""The message validators refuse every non-finite or unphysical float and every oversized message, with its reason.

Pure and fast: messages are plain namespaces (the decoders read attributes only), so no rclpy is needed. The
properties run under hypothesis when it is installed, else over a fixed set of seeded random cases.
"""

from __future__ import annotations

import math
import random
from types import SimpleNamespace

import numpy as np
import pytest

from controlled_islanding.core.dse import MachineData
from controlled_islanding.core.grid import DYNAMIC_FIELDS
from controlled_islanding.wire.messages import MAX_MODEL_NAME, Limits, MessageError, grid_from_snapshot, groups_from_msg

try:
    from hypothesis import given, settings
    from hypothesis import strategies as st
except ImportError:  # the fallback below draws the same cases from a seeded generator
    given = None

SNAPSHOT_FLOATS = ('branch_p_from_mw', 'branch_p_to_mw', 'generator_p_mw', 'generator_p_max_mw', 'generator_xq_pu',
                   'generator_ra_pu', 'load_p_mw', 'load_q_mvar')
NON_NEGATIVE = ('generator_xq_pu', 'generator_ra_pu')
NON_FINITE = (math.nan, math.inf, -math.inf)


def snapshot(n_gen: int = 2) -> SimpleNamespace:
    """Return a valid NetworkSnapshot-like object: a chain of n_gen + 1 buses, a generator on all but the last."""
    buses = list(range(1, n_gen + 2))
    return SimpleNamespace(
        case_name='toy', base_mva=100.0, bus_numbers=buses,
        branch_ids=[f'{b}-{b + 1}' for b in buses[:-1]], branch_breaker_ids=[],
        branch_from_bus=buses[:-1], branch_to_bus=buses[1:], branch_in_service=[True] * n_gen,
        branch_p_from_mw=[10.0] * n_gen, branch_p_to_mw=[-9.9] * n_gen,
        generator_names=[f'G{b}' for b in buses[:-1]], generator_bus=buses[:-1], generator_p_mw=[50.0] * n_gen,
        generator_p_max_mw=[80.0] * n_gen, generator_xq_pu=[0.2] * n_gen, generator_ra_pu=[0.0] * n_gen,
        load_bus=[buses[-1]], load_p_mw=[100.0], load_q_mvar=[20.0])


def groups(n: int = 3) -> SimpleNamespace:
    """Return a valid CoherentGroups-like object with n generators in two groups."""
    return SimpleNamespace(
        generator_names=[f'G{i}' for i in range(n)], generator_buses=list(range(1, n + 1)),
        group=[0] + [1] * (n - 1), k=2, method='dtw', distance=[0.5] * (n * n), unobserved_generator_names=[],
        header=SimpleNamespace(stamp=SimpleNamespace(sec=10, nanosec=0)))


def reason(decode, msg) -> str:
    with pytest.raises(MessageError) as info:
        decode(msg)
    return info.value.reason


class Huge:
    """A sequence that claims a huge length and fails the test if any element is ever touched."""

    def __init__(self, n: int) -> None:
        self.n = n

    def __len__(self) -> int:
        return self.n

    def __iter__(self):
        raise AssertionError('an oversized array was read element by element before its size was checked')

    def __getitem__(self, index):
        raise AssertionError('an oversized array was read element by element before its size was checked')

    def __array__(self, *args, **kwargs):
        raise AssertionError('an oversized array was converted before its size was checked')


def test_the_valid_snapshot_and_groups_decode():
    grid = grid_from_snapshot(snapshot())
    assert [g.xq_pu for g in grid.generators] == [0.2, 0.2]
    assert groups_from_msg(groups()).k == 2


@pytest.mark.parametrize('field', SNAPSHOT_FLOATS)
@pytest.mark.parametrize('bad', NON_FINITE, ids=('nan', 'inf', '-inf'))
def test_every_snapshot_float_array_refuses_nan_and_inf(field, bad):
    msg = snapshot()
    getattr(msg, field)[-1] = bad
    assert reason(grid_from_snapshot, msg) == 'nan_value'


@pytest.mark.parametrize('field', NON_NEGATIVE)
def test_a_negative_reactance_or_resistance_is_refused_as_unphysical(field):
    msg = snapshot()
    getattr(msg, field)[0] = -0.01
    assert reason(grid_from_snapshot, msg) == 'bad_value'


def test_a_zero_reactance_and_resistance_are_physical():
    msg = snapshot()
    msg.generator_xq_pu[0] = msg.generator_ra_pu[0] = 0.0
    assert grid_from_snapshot(msg).generators[0].xq_pu == 0.0


@pytest.mark.parametrize('base', (0.0, -100.0))
def test_a_base_that_is_not_positive_is_refused(base):
    msg = snapshot()
    msg.base_mva = base
    assert reason(grid_from_snapshot, msg) == 'bad_value'


@pytest.mark.parametrize('base', NON_FINITE, ids=('nan', 'inf', '-inf'))
def test_a_non_finite_base_is_refused(base):
    msg = snapshot()
    msg.base_mva = base
    assert reason(grid_from_snapshot, msg) == 'nan_value'


def test_a_nan_reactance_snapshot_cannot_reach_the_rotor_angle_estimator():
    # The crash of the issue: a NaN xq made core.rotor_angle raise on every frame.
    msg = snapshot()
    msg.generator_xq_pu = [math.nan] * 2
    assert reason(grid_from_snapshot, msg) == 'nan_value'


# A two-axis machine (GENROU's data without the sub-transient part) and a machine without dynamic data.
MACHINE = {'m_s': 8.0, 'd_pu': 0.0, 'xd_pu': 1.8, 'xd1_pu': 0.6, 'xq1_pu': 0.8, 'xd2_pu': math.nan,
           'xq2_pu': math.nan, 'xl_pu': 0.15, 'td10_s': 6.5, 'tq10_s': 0.2, 'td20_s': math.nan, 'tq20_s': math.nan,
           's10': 0.09, 's12': 0.38}


def with_machine_data(msg: SimpleNamespace) -> SimpleNamespace:
    msg.generator_model = ['GENROU', '']
    for name, value in MACHINE.items():
        setattr(msg, f'generator_{name}', [value, math.nan])
    return msg


def test_machine_data_is_optional_and_nan_or_empty_means_unknown():
    old = grid_from_snapshot(snapshot())  # a message type older than the fields, as in an old bag
    assert all(np.isnan(getattr(g, f)) for g in old.generators for f in DYNAMIC_FIELDS)
    assert MachineData.of_generators(old.generators).richest_model().tolist() == ['steady_state'] * 2
    grid = grid_from_snapshot(with_machine_data(snapshot()))
    assert [g.model for g in grid.generators] == ['GENROU', '']
    assert grid.generators[0].xd1_pu == 0.6 and np.isnan(grid.generators[1].m_s)
    assert MachineData.of_generators(grid.generators).richest_model().tolist() == ['two_axis', 'steady_state']
    msg = with_machine_data(snapshot())
    msg.generator_model, msg.generator_s12 = [], []
    assert [g.model for g in grid_from_snapshot(msg).generators] == ['', '']


@pytest.mark.parametrize('field', DYNAMIC_FIELDS)
def test_machine_data_is_never_inf_negative_or_of_another_length(field):
    for bad, expected in ((math.inf, 'nan_value'), (-math.inf, 'nan_value'), (-1e-9, 'bad_value')):
        msg = with_machine_data(snapshot())
        getattr(msg, f'generator_{field}')[1] = bad
        assert reason(grid_from_snapshot, msg) == expected, bad
    msg = with_machine_data(snapshot())
    getattr(msg, f'generator_{field}').append(1.0)
    assert reason(grid_from_snapshot, msg) == 'array_length'


def test_machine_model_names_are_one_per_generator_and_short():
    msg = with_machine_data(snapshot())
    msg.generator_model = ['GENROU']
    assert reason(grid_from_snapshot, msg) == 'array_length'
    msg.generator_model = ['GENROU', 'X' * (MAX_MODEL_NAME + 1)]
    assert reason(grid_from_snapshot, msg) == 'bad_value'


def test_bus_angles_are_optional_one_per_bus_and_finite():
    msg = snapshot()
    assert grid_from_snapshot(msg).bus_angle_rad is None  # a message from before the field
    msg.bus_voltage_angle_rad = []
    assert grid_from_snapshot(msg).bus_angle_rad is None
    msg.bus_voltage_angle_rad = [0.0, -0.1, -0.2]
    grid = grid_from_snapshot(msg)
    assert list(grid.bus_angles_at([3, 1, 99])[:2]) == [-0.2, 0.0] and math.isnan(grid.bus_angles_at([99])[0])
    msg.bus_voltage_angle_rad = [0.0, -0.1]
    assert reason(grid_from_snapshot, msg) == 'array_length'
    msg.bus_voltage_angle_rad = [0.0, math.nan, -0.2]
    assert reason(grid_from_snapshot, msg) == 'nan_value'


SNAPSHOT_CAPS = {
    'max_buses': ('bus_numbers', 'bus_voltage_angle_rad'),
    'max_branches': ('branch_ids', 'branch_breaker_ids', 'branch_from_bus', 'branch_to_bus', 'branch_in_service',
                     'branch_p_from_mw', 'branch_p_to_mw'),
    'max_generators': ('generator_names', 'generator_bus', 'generator_p_mw', 'generator_p_max_mw',
                       'generator_xq_pu', 'generator_ra_pu', 'generator_model')
                      + tuple(f'generator_{f}' for f in DYNAMIC_FIELDS),
    'max_loads': ('load_bus', 'load_p_mw', 'load_q_mvar'),
}


@pytest.mark.parametrize('cap,field', [(c, f) for c, fields in SNAPSHOT_CAPS.items() for f in fields])
def test_every_snapshot_array_is_capped_before_any_element_is_read(cap, field):
    msg = snapshot()
    setattr(msg, field, Huge(10**9))
    assert reason(grid_from_snapshot, msg) == 'too_large'


def test_the_snapshot_caps_are_arguments():
    msg = snapshot(n_gen=3)
    assert reason(lambda m: grid_from_snapshot(m, Limits(max_generators=2)), msg) == 'too_large'
    assert reason(lambda m: grid_from_snapshot(m, Limits(max_buses=3)), msg) == 'too_large'
    assert reason(lambda m: grid_from_snapshot(m, Limits(max_branches=2)), msg) == 'too_large'
    assert reason(lambda m: grid_from_snapshot(m, Limits(max_loads=0)), msg) == 'too_large'
    exact = Limits(max_buses=4, max_branches=3, max_generators=3, max_loads=1)
    assert len(grid_from_snapshot(msg, exact).generators) == 3


def test_the_default_limits_are_generous_but_bounded():
    limits = Limits()
    assert 10_000 <= limits.max_buses < 10**6 and 10_000 <= limits.max_branches < 10**6
    assert 1_000 <= limits.max_generators < 10**5 and 10_000 <= limits.max_loads < 10**6
    with pytest.raises(AttributeError):
        limits.max_buses = 1  # frozen: a node cannot loosen its caps by accident


@pytest.mark.parametrize('bad,expected', [(math.nan, 'nan_value'), (math.inf, 'nan_value'), (-1.0, 'bad_value')])
def test_groups_distances_must_be_finite_and_non_negative(bad, expected):
    msg = groups()
    msg.distance[4] = bad
    assert reason(groups_from_msg, msg) == expected


def test_unobserved_generators_are_named_once_and_never_also_grouped():
    msg = groups()
    msg.unobserved_generator_names = ['G9', 'G8']
    assert groups_from_msg(msg).unobserved == ('G8', 'G9')
    msg.unobserved_generator_names = ['G9', 'G9']
    assert reason(groups_from_msg, msg) == 'unknown_id'
    msg.unobserved_generator_names = ['G1']
    assert reason(groups_from_msg, msg) == 'unknown_id'


@pytest.mark.parametrize('field', ('generator_names', 'generator_buses', 'group', 'unobserved_generator_names'))
def test_groups_are_capped_before_any_element_is_read(field):
    msg = groups()
    setattr(msg, field, Huge(10**9))
    assert reason(groups_from_msg, msg) == 'too_large'
    assert reason(lambda m: groups_from_msg(m, Limits(max_generators=2)), groups()) == 'too_large'


# Properties: whatever the network, one poisoned value anywhere is refused with its reason.

def poison_snapshot(n_gen: int, field: str, index: int, value: float) -> tuple[SimpleNamespace, str]:
    msg = snapshot(n_gen)
    values = getattr(msg, field)
    values[index % len(values)] = value
    expected = 'nan_value' if not math.isfinite(value) else 'bad_value'
    return msg, expected


def check_poisoned(n_gen: int, field: str, index: int, value: float) -> None:
    msg, expected = poison_snapshot(n_gen, field, index, value)
    assert reason(grid_from_snapshot, msg) == expected


def check_physical_values_pass(n_gen: int, xq: list[float], ra: list[float]) -> None:
    msg = snapshot(n_gen)
    msg.generator_xq_pu, msg.generator_ra_pu = xq[:n_gen], ra[:n_gen]
    grid = grid_from_snapshot(msg)
    assert np.allclose([g.xq_pu for g in grid.generators], xq[:n_gen])


if given is not None:
    poisoned_field = st.sampled_from(SNAPSHOT_FLOATS)
    non_finite = st.sampled_from(NON_FINITE)
    negative = st.floats(max_value=-1e-12, allow_nan=False, allow_infinity=False)

    @settings(max_examples=200, deadline=None)
    @given(n_gen=st.integers(1, 30), field=poisoned_field, index=st.integers(0, 1000), value=non_finite)
    def test_property_any_non_finite_value_is_refused(n_gen, field, index, value):
        check_poisoned(n_gen, field, index, value)

    @settings(max_examples=200, deadline=None)
    @given(n_gen=st.integers(1, 30), field=st.sampled_from(NON_NEGATIVE), index=st.integers(0, 1000),
           value=negative)
    def test_property_any_negative_reactance_is_refused(n_gen, field, index, value):
        check_poisoned(n_gen, field, index, value)

    @settings(max_examples=100, deadline=None)
    @given(n_gen=st.integers(1, 10),
           xq=st.lists(st.floats(0.0, 1e3), min_size=10, max_size=10),
           ra=st.lists(st.floats(0.0, 1e3), min_size=10, max_size=10))
    def test_property_physical_reactances_pass(n_gen, xq, ra):
        check_physical_values_pass(n_gen, xq, ra)

else:
    def test_property_any_non_finite_value_is_refused():
        rng = random.Random(10)
        for _ in range(200):
            check_poisoned(rng.randint(1, 30), rng.choice(SNAPSHOT_FLOATS), rng.randint(0, 1000),
                           rng.choice(NON_FINITE))

    def test_property_any_negative_reactance_is_refused():
        rng = random.Random(11)
        for _ in range(200):
            check_poisoned(rng.randint(1, 30), rng.choice(NON_NEGATIVE), rng.randint(0, 1000),
                           -10 ** rng.uniform(-12, 300))

    def test_property_physical_reactances_pass():
        rng = random.Random(12)
        for _ in range(100):
            check_physical_values_pass(rng.randint(1, 10), [rng.uniform(0, 1e3) for _ in range(10)],
                                       [rng.uniform(0, 1e3) for _ in range(10)])
