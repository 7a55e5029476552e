"""Vision: the pipe-rack tracker and the downward ground odometer."""
