"""One robot: the sans-I/O RobotNode, transports, link models and the asyncio runtime."""
