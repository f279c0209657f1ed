"""fleethealth: health monitoring of aircraft actuators across a fleet."""

__version__ = "0.1.0"
