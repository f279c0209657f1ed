"""API keys and operators: who calls, for which operator, with which scopes."""
