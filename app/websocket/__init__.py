"""The server side of WebSocket streaming: live ingest with results pushed back, and fleet
event subscriptions (``hub`` routes what the processor commits to the connections)."""
