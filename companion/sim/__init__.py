"""The simulator: scene renderers, vehicle dynamics, the scripted fake autopilot, `companion sim`."""
