"""The daemon's control API: HTTP server (aiohttp), mission store, async client and CLI commands.

See `docs/drivers.md` for the routes and the daemon-facing interfaces.
"""

from drivers.api.client import (
    DEFAULT_URL,
    ApiClient,
    ApiError,
    add_client_arguments,
    add_mission_subcommands,
    format_missions,
    format_status,
    mission_cli,
    resolve_endpoint,
    status_cli,
)
from drivers.api.server import (
    API_PREFIX,
    ApiServer,
    MissionController,
    StatusProvider,
    Validator,
    default_validator,
    read_token_file,
)
from drivers.api.store import MissionStore, is_valid_id, mission_id_from_name

__all__ = [
    "API_PREFIX",
    "DEFAULT_URL",
    "ApiClient",
    "ApiError",
    "ApiServer",
    "MissionController",
    "MissionStore",
    "StatusProvider",
    "Validator",
    "add_client_arguments",
    "add_mission_subcommands",
    "default_validator",
    "format_missions",
    "format_status",
    "is_valid_id",
    "mission_cli",
    "mission_id_from_name",
    "read_token_file",
    "resolve_endpoint",
    "status_cli",
]
