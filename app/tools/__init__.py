"""Command-line tools that feed a running fleethealth server: ``simulate`` and ``replay``."""
