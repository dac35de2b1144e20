"""Simulation of what lies beyond the host: the hand, the device, the link, the actuator."""
