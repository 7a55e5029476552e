"""Data files shipped inside the package: the simulator's default config, rack and missions.

`data_path("sim_default.toml")` resolves a file here, so an installed
package finds them without the source tree.
"""

from __future__ import annotations

from pathlib import Path

__all__ = ["DATA_DIR", "data_path"]

DATA_DIR = Path(__file__).resolve().parent


def data_path(relative: str) -> Path:
    """Absolute path of a packaged data file (``racks/sweep_5pipe.toml``, ``missions/...``)."""
    path = DATA_DIR / relative
    if not path.exists():
        from companion.errors import ConfigError

        raise ConfigError(f"packaged data file missing: {relative} (looked in {DATA_DIR})")
    return path
