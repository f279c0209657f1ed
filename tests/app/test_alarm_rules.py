"""The alarm rules, as a pure function: raise, change, re-trigger and clear per cause; and the
open-fault list, which follows the same rules for faults."""

from __future__ import annotations

from app.alarms.rules import Decision, OpenAlarm, RuleEvent, decide
from app.faults.service import open_faults
from app.models import EstimatorEventRow


def status(to: str, reasons: list[str] | None = None) -> RuleEvent:
    return RuleEvent("status_changed", {"to": to, "reasons": reasons or []})


def fault(kind: str, component: str, estimator: str = "stmmae", **detail: object) -> RuleEvent:
    return RuleEvent(kind, {"estimator": estimator, "detail": {"component": component, **detail}})


def actions(ds: list[Decision]) -> list[tuple[str, str, str, int, str]]:
    return [(d.action, d.cause, d.subject, d.event_index, d.severity) for d in ds]


def test_status_raises_escalates_and_clears_one_alarm() -> None:
    ds = decide({}, [status("watch"), status("alert", ["drift"]), status("failed"), status("ok")])
    assert actions(ds) == [
        ("raise", "status", "", 0, "warning"),
        ("update", "status", "", 1, "major"),
        ("update", "status", "", 2, "critical"),
        ("clear", "status", "", 3, "critical"),
    ]
    assert ds[1].message == "status alert: drift"


def test_an_open_alarm_is_not_raised_again() -> None:
    open_ = {("status", ""): OpenAlarm("minor")}
    assert actions(decide(open_, [status("unknown")])) == [("touch", "status", "", 0, "minor")]
    assert decide(open_, [status("learning")])[0].action == "clear"
    # Nothing open, nothing to clear.
    assert decide({}, [status("ok")]) == []


def test_faults_per_component_with_revisions_and_blanket_clearance() -> None:
    ds = decide(
        {},
        [
            fault("fault_detected", "rudder"),
            fault("fault_detected", "rudder"),  # still the same fault: re-trigger
            fault("fault_detected", "aileron", estimator="darr_fekf"),
            fault("fault_cleared", "rudder"),
            fault("fault_detected", "elevator"),
            fault("fault_cleared", "unknown-component"),  # names none open: clears all of stmmae's
        ],
    )
    assert actions(ds) == [
        ("raise", "fault", "rudder", 0, "major"),
        ("touch", "fault", "rudder", 1, "major"),
        ("raise", "fault", "aileron", 2, "major"),
        ("clear", "fault", "rudder", 3, "major"),
        ("raise", "fault", "elevator", 4, "major"),
        ("clear", "fault", "elevator", 5, "major"),
    ]
    # A revised detection replaces the estimator's other components, not another estimator's.
    open_ = {
        ("fault", "s1"): OpenAlarm("major", "darr_fekf"),
        ("fault", "x"): OpenAlarm("major", "stmmae"),
    }
    ds = decide(open_, [fault("fault_detected", "s2", estimator="darr_fekf", update=True)])
    assert actions(ds) == [("clear", "fault", "s1", 0, "major"), ("raise", "fault", "s2", 0, "major")]


def test_a_group_handed_to_its_half_clears_the_group_alone() -> None:
    """A group of two halves detected, then one half isolated: the half's alarm is raised and
    the group's cleared as isolated; a hand-over naming no open group clears nothing else."""
    ds = decide(
        {},
        [
            fault("fault_detected", "aileron", candidates=["aileron_left", "aileron_right"]),
            fault("fault_detected", "aileron_right"),
            fault("fault_cleared", "aileron", isolated_as="aileron_right"),
            fault("fault_cleared", "elevator", isolated_as="elevator_left"),
        ],
    )
    assert actions(ds) == [
        ("raise", "fault", "aileron", 0, "major"),
        ("raise", "fault", "aileron_right", 1, "major"),
        ("clear", "fault", "aileron", 2, "major"),
    ]
    assert ds[2].message == "isolated as aileron_right"


def test_rul_and_dn_thresholds() -> None:
    rul = lambda to: RuleEvent("rul_threshold_crossed", {"estimator": "dekf", "detail": {"to": to}})  # noqa: E731
    dn = lambda to: RuleEvent("dn_threshold_crossed", {"estimator": "dekf", "detail": {"to": to}})  # noqa: E731
    ds = decide({}, [rul("watch"), dn("alert"), rul("unknown"), rul("failed"), dn("watch"), dn("ok"), rul("ok")])
    assert actions(ds) == [
        ("raise", "rul", "", 0, "warning"),
        ("raise", "dn", "", 1, "major"),
        ("update", "rul", "", 3, "critical"),  # unknown says nothing about the life left
        ("update", "dn", "", 4, "warning"),
        ("clear", "dn", "", 5, "warning"),
        ("clear", "rul", "", 6, "critical"),
    ]


def test_other_events_raise_nothing() -> None:
    assert decide({}, [RuleEvent("identified", {}), RuleEvent("alarm_raised", {})]) == []


def test_the_fault_list_hands_a_group_to_its_half() -> None:
    """The open faults follow the same rule as the alarms: the group's detection is closed by
    its hand-over, the half's stays open, and a hand-over whose group is not in the rows read
    (an older detection outside them) closes nothing else."""

    def row(i: int, kind: str, component: str, **detail: object) -> EstimatorEventRow:
        return EstimatorEventRow(
            id=i,
            estimator="stmmae",
            t_s=float(i),
            kind=kind,
            detail={"component": component, **detail},
        )

    rows = [
        row(1, "fault_detected", "aileron", candidates=["aileron_left", "aileron_right"]),
        row(2, "fault_detected", "aileron_right"),
        row(3, "fault_cleared", "aileron", isolated_as="aileron_right"),
    ]
    assert [r.detail["component"] for r in open_faults(rows)] == ["aileron_right"]
    assert [r.detail["component"] for r in open_faults(rows[1:])] == ["aileron_right"]
    # a plain clearance naming nothing open still clears all of the estimator's
    assert open_faults([*rows[1:], row(4, "fault_cleared", "rudder")]) == []
