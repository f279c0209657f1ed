"""Aircraft, actuators, actuator kinds and the fleet board."""
