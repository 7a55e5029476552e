"""LiPo battery model: state of charge drained by the load, open-circuit voltage curve, internal resistance.

Pure functions on frozen dataclasses. Current draw follows the thrust: hover
current scaled by (thrust / weight)^1.5 (momentum theory: power ∝ thrust^1.5),
plus the avionics draw; an idle current when disarmed.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from companion.errors import InputError

__all__ = [
    "BatteryParams",
    "BatteryState",
    "battery_current_a",
    "initial_battery",
    "open_circuit_voltage_per_cell_v",
    "step_battery",
]

# Resting LiPo cell voltage against state of charge (fraction 0..1).
_SOC = np.array([0.0, 0.05, 0.10, 0.20, 0.30, 0.40, 0.50, 0.60, 0.70, 0.80, 0.90, 1.0])
_OCV_V = np.array([3.27, 3.50, 3.61, 3.69, 3.73, 3.77, 3.80, 3.84, 3.90, 3.98, 4.08, 4.20])


@dataclass(frozen=True)
class BatteryParams:
    """Pack parameters: `cells` in series, capacity (mAh), internal resistance (ohm, whole pack), currents (A)."""

    cells: int = 4
    capacity_mah: float = 5000.0
    internal_resistance_ohm: float = 0.025
    hover_current_a: float = 18.0
    avionics_current_a: float = 0.6
    idle_armed_current_a: float = 2.5
    initial_soc: float = 1.0
    low_remaining_pct: float = 25.0
    critical_remaining_pct: float = 10.0

    def __post_init__(self) -> None:
        if not 1 <= self.cells <= 14:  # BATTERY_STATUS carries at most 14 cell voltages
            raise InputError(f"BatteryParams.cells must be in [1, 14], got {self.cells}")
        if not self.capacity_mah > 0.0:
            raise InputError(f"BatteryParams.capacity_mah must be > 0, got {self.capacity_mah}")
        if not 0.0 <= self.initial_soc <= 1.0:
            raise InputError(f"BatteryParams.initial_soc must be in [0, 1], got {self.initial_soc}")


@dataclass(frozen=True)
class BatteryState:
    """Battery at one instant: SoC (0..1), charge used (mAh), energy used (J), terminal voltage (V), current (A)."""

    soc: float
    consumed_mah: float
    consumed_energy_j: float
    voltage_v: float
    current_a: float

    @property
    def remaining_pct(self) -> float:
        """Remaining charge in percent (0..100)."""
        return 100.0 * self.soc


def open_circuit_voltage_per_cell_v(soc: float) -> float:
    """Resting cell voltage (V) at state of charge `soc` (0..1, clipped)."""
    return float(np.interp(min(max(soc, 0.0), 1.0), _SOC, _OCV_V))


def initial_battery(params: BatteryParams) -> BatteryState:
    """A rested battery at the configured initial state of charge."""
    voltage = params.cells * open_circuit_voltage_per_cell_v(params.initial_soc)
    return BatteryState(params.initial_soc, 0.0, 0.0, voltage, 0.0)


def battery_current_a(params: BatteryParams, armed: bool, airborne: bool, thrust_ratio: float) -> float:
    """Current draw (A): `thrust_ratio` = thrust / (mass g) (1 at hover)."""
    if not armed:
        return params.avionics_current_a
    if not airborne:
        return params.avionics_current_a + params.idle_armed_current_a
    return params.avionics_current_a + params.hover_current_a * math.pow(max(thrust_ratio, 0.0), 1.5)


def step_battery(state: BatteryState, params: BatteryParams, current_a: float, dt_s: float) -> BatteryState:
    """Drain `current_a` amperes for `dt_s` seconds; return the new state (terminal voltage under load)."""
    if dt_s < 0.0 or not math.isfinite(current_a):
        raise InputError(f"step_battery needs dt_s >= 0 and a finite current, got {dt_s}, {current_a}")
    used_mah = current_a * dt_s / 3.6
    consumed = state.consumed_mah + used_mah
    soc = max(0.0, params.initial_soc - consumed / params.capacity_mah)
    ocv = params.cells * open_circuit_voltage_per_cell_v(soc)
    voltage = max(0.0, ocv - current_a * params.internal_resistance_ohm)
    energy = state.consumed_energy_j + voltage * current_a * dt_s
    return replace(
        state, soc=soc, consumed_mah=consumed, consumed_energy_j=energy, voltage_v=voltage, current_a=current_a
    )
