"""URL paths of the API, shared by the REST clients and the WebSocket streamer."""

from __future__ import annotations

from urllib.parse import quote

__all__ = ["actuator_path", "aircraft_path", "segment", "ws_url"]


def segment(value: str) -> str:
    """One path segment, percent-encoded (a tail may hold ``/``)."""
    return quote(value, safe="")


def aircraft_path(tail: str) -> str:
    """``/v1/aircraft/{tail}``."""
    return f"/v1/aircraft/{segment(tail)}"


def actuator_path(tail: str, actuator_id: str) -> str:
    """``/v1/aircraft/{tail}/actuators/{actuator_id}``."""
    return f"{aircraft_path(tail)}/actuators/{segment(actuator_id)}"


def ws_url(base_url: str, path: str) -> str:
    """The WebSocket URL of ``path`` on a server given by its HTTP(S) address."""
    if base_url.startswith("https://"):
        return "wss://" + base_url[len("https://") :].rstrip("/") + path
    if base_url.startswith("http://"):
        return "ws://" + base_url[len("http://") :].rstrip("/") + path
    return base_url.rstrip("/") + path
