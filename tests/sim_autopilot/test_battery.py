"""Battery model: drains with load, sags under current, rests at the OCV curve."""

from __future__ import annotations

import itertools

import pytest

from companion.errors import InputError
from companion.sim.autopilot.battery import (
    BatteryParams,
    battery_current_a,
    initial_battery,
    open_circuit_voltage_per_cell_v,
    step_battery,
)


def test_full_pack_rests_at_4v2_per_cell() -> None:
    params = BatteryParams(cells=4)
    b = initial_battery(params)
    assert b.voltage_v == pytest.approx(16.8)
    assert b.remaining_pct == pytest.approx(100.0)


def test_ocv_is_monotonic_in_state_of_charge() -> None:
    volts = [open_circuit_voltage_per_cell_v(s / 20.0) for s in range(21)]
    assert all(b > a for a, b in itertools.pairwise(volts))
    assert open_circuit_voltage_per_cell_v(-1.0) == open_circuit_voltage_per_cell_v(0.0)


def test_current_follows_thrust_and_arming() -> None:
    p = BatteryParams()
    idle = battery_current_a(p, armed=False, airborne=False, thrust_ratio=0.0)
    ground = battery_current_a(p, armed=True, airborne=False, thrust_ratio=1.0)
    hover = battery_current_a(p, armed=True, airborne=True, thrust_ratio=1.0)
    climb = battery_current_a(p, armed=True, airborne=True, thrust_ratio=1.3)
    assert idle < ground < hover < climb
    assert hover == pytest.approx(p.avionics_current_a + p.hover_current_a)
    assert climb == pytest.approx(p.avionics_current_a + p.hover_current_a * 1.3**1.5)


def test_drain_integrates_charge_and_sags_under_load() -> None:
    p = BatteryParams(capacity_mah=5000.0)
    b = initial_battery(p)
    for _ in range(600):  # 10 minutes at 18.6 A in 1 s steps
        b = step_battery(b, p, 18.6, 1.0)
    assert b.consumed_mah == pytest.approx(18.6 * 600 / 3.6)
    assert b.remaining_pct == pytest.approx(100.0 * (1 - 3100.0 / 5000.0))
    loaded = b.voltage_v
    rested = step_battery(b, p, 0.0, 1e-9).voltage_v
    assert rested - loaded == pytest.approx(18.6 * p.internal_resistance_ohm, rel=1e-3)
    assert b.consumed_energy_j > 0.0
    with pytest.raises(InputError):
        step_battery(b, p, 1.0, -1.0)


def test_params_are_validated() -> None:
    with pytest.raises(InputError):
        BatteryParams(cells=0)
    with pytest.raises(InputError):
        BatteryParams(initial_soc=1.5)
