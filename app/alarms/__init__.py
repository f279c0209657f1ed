"""Alarms: raised by rules from logged fleet events, acknowledged and cleared by people."""
