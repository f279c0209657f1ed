"""The dashboard: a fleet board and per-actuator plots, served by the app itself."""
