"""Pure numerical estimators for actuator health (no web, no database).

See :mod:`estimators.base` for the contract and :mod:`estimators.registry` for the kinds.
"""
