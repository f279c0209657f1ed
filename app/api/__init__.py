"""HTTP routers: they speak HTTP only and leave decisions to the services."""
