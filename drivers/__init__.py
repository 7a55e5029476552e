"""Adapters to the world: cameras, the MAVLink transport, the control API server."""
