"""companion: vision-based localization, missions and safety for inspection drones."""

from companion.errors import CompanionError

__all__ = ["CompanionError", "__version__"]
__version__ = "0.1.0"
