"""Fixtures of the ArduPilot tier: every test here talks to a fresh real ArduCopter SITL (real time).

The tests are marked `ardupilot` (`pytest -m ardupilot` runs this tier alone) and skip with the
reason when no SITL binary is found (`$COMPANION_ARDUPILOT_SITL` or ../shared/ardupilot/arducopter);
`.ci/run` fails if they were skipped while ../shared/ardupilot/arducopter exists.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from companion.sim.ardupilot_sitl import sitl_binary

HERE = Path(__file__).resolve().parent


def pytest_collection_modifyitems(config: pytest.Config, items: list[pytest.Item]) -> None:
    for item in items:
        if Path(str(item.fspath)).resolve().parent == HERE:
            item.add_marker(pytest.mark.ardupilot)
            item.add_marker(pytest.mark.timeout(420))


def pytest_terminal_summary(terminalreporter: pytest.TerminalReporter) -> None:
    from sitl_tests.ardupilot.harness import FIGURES

    if FIGURES:
        terminalreporter.section("figures measured on the ArduCopter SITL")
        for line in FIGURES:
            terminalreporter.write_line(line)


@pytest.fixture
def sitl_available() -> Path:
    binary = sitl_binary()
    if binary is None:
        pytest.skip("no ArduCopter SITL binary: set COMPANION_ARDUPILOT_SITL or put ../shared/ardupilot/arducopter "
                    "beside the repository")
    return binary
