"""The HTTP API (contract sections 1-3): app factory (:func:`services.api.app.create_app`),
dependencies, routes."""
