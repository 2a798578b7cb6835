"""The HTTP API (FastAPI): REST API v1, problem+json errors, metrics, the dashboard."""
