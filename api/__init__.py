"""The HTTP API (FastAPI). Arrives with issue 3."""
