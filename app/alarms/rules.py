"""The alarm rules: which logged events raise, change, re-trigger or clear an alarm.

A pure function over the actuator's open alarms and the events of one apply, in order; the
service carries the decisions out in the same transaction. Causes and what they watch:

* ``status``: the actuator's worst status. ``watch`` raises a ``warning``, ``unknown`` a
  ``minor``, ``alert`` a ``major`` and ``failed`` a ``critical`` alarm; a change between these
  changes the open alarm's severity; ``ok`` or ``learning`` clears it.
* ``fault`` (subject: the component): ``fault_detected`` raises a ``major`` alarm per
  component, re-triggers it while open; ``fault_cleared`` clears it (a clearance naming no open
  component clears all of that estimator's unless it hands a group's episode to one of its
  halves, ``"isolated_as"``, and a revised detection, ``"update": true``, replaces that
  estimator's other components, as the fault list does).
* ``rul``: ``rul_threshold_crossed`` to ``watch`` / ``alert`` / ``failed`` raises or changes
  (``warning`` / ``major`` / ``critical``); back to ``ok`` or ``learning`` clears.
* ``dn``: ``dn_threshold_crossed`` (normalized deterioration) to ``watch`` / ``alert`` raises
  or changes (``warning`` / ``major``); back to ``ok`` clears.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

SEVERITIES = ("critical", "major", "minor", "warning")
CAUSES = ("status", "fault", "rul", "dn")
Action = Literal["raise", "update", "touch", "clear"]

STATUS_SEVERITY = {"failed": "critical", "alert": "major", "unknown": "minor", "watch": "warning"}
STATUS_CLEARS = frozenset({"ok", "learning"})
RUL_SEVERITY = {"failed": "critical", "alert": "major", "watch": "warning"}
RUL_CLEARS = frozenset({"ok", "learning"})
DN_SEVERITY = {"alert": "major", "watch": "warning"}
DN_CLEARS = frozenset({"ok"})
FAULT_SEVERITY = "major"

Key = tuple[str, str]  # (cause, subject)


@dataclass(frozen=True)
class OpenAlarm:
    """What the rules need of an open alarm."""

    severity: str
    estimator: str | None = None


@dataclass(frozen=True)
class RuleEvent:
    """What the rules need of a logged event: its type and its own fields."""

    type: str
    body: Mapping[str, Any] = field(default_factory=dict)


@dataclass(frozen=True)
class Decision:
    """Raise, change the severity of, re-trigger or clear the alarm ``(cause, subject)``
    because of ``events[event_index]``."""

    action: Action
    cause: str
    subject: str
    event_index: int
    severity: str
    message: str
    estimator: str | None = None


def decide(open_alarms: Mapping[Key, OpenAlarm], events: Sequence[RuleEvent]) -> list[Decision]:
    """The decisions of ``events`` (in order) over the alarms open before them."""
    state = dict(open_alarms)
    out: list[Decision] = []

    def level(i: int, key: Key, severity: str, message: str, estimator: str | None) -> None:
        cur = state.get(key)
        if cur is None:
            action: Action = "raise"
        elif cur.severity != severity:
            action = "update"
        else:
            action = "touch"
        state[key] = OpenAlarm(severity, estimator if cur is None else cur.estimator)
        out.append(Decision(action, key[0], key[1], i, severity, message, estimator))

    def clear(i: int, key: Key, message: str) -> None:
        cur = state.pop(key, None)
        if cur is not None:
            out.append(Decision("clear", key[0], key[1], i, cur.severity, message, cur.estimator))

    for i, ev in enumerate(events):
        b = ev.body
        estimator = b.get("estimator")
        if ev.type == "status_changed":
            to = str(b.get("to"))
            if to in STATUS_SEVERITY:
                reasons = "; ".join(str(r) for r in b.get("reasons") or [])
                level(
                    i,
                    ("status", ""),
                    STATUS_SEVERITY[to],
                    f"status {to}" + (f": {reasons}" if reasons else ""),
                    None,
                )
            elif to in STATUS_CLEARS:
                clear(i, ("status", ""), f"status back to {to}")
        elif ev.type in ("fault_detected", "fault_cleared"):
            detail = b.get("detail") or {}
            component = str(detail.get("component"))
            mine = [k for k, a in state.items() if k[0] == "fault" and a.estimator == estimator]
            if ev.type == "fault_detected":
                if detail.get("update"):
                    for k in mine:
                        if k[1] != component:
                            clear(i, k, f"superseded by a revised detection ({component})")
                level(
                    i,
                    ("fault", component),
                    FAULT_SEVERITY,
                    f"fault detected: {component}",
                    estimator,
                )
            elif ("fault", component) in state:
                half = detail.get("isolated_as")
                why = f"isolated as {half}" if half else f"fault cleared: {component}"
                clear(i, ("fault", component), why)
            elif detail.get("isolated_as"):
                pass  # a group's episode handed to its half, whose own alarm stays open
            else:
                for k in mine:
                    clear(i, k, f"fault cleared by {estimator}")
        elif ev.type in ("rul_threshold_crossed", "dn_threshold_crossed"):
            detail = b.get("detail") or {}
            to = str(detail.get("to"))
            cause, severities, clears, what = (
                ("rul", RUL_SEVERITY, RUL_CLEARS, "remaining useful life")
                if ev.type == "rul_threshold_crossed"
                else ("dn", DN_SEVERITY, DN_CLEARS, "normalized deterioration")
            )
            if to in severities:
                level(i, (cause, ""), severities[to], f"{what} at {to}", estimator)
            elif to in clears:
                clear(i, (cause, ""), f"{what} back to {to}")
    return out
