"""The REST service: app factory, shared dependencies, one router per resource."""
