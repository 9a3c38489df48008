"""The wire: slots, stacks, their merge rule and the msgpack codec (sans-I/O)."""
